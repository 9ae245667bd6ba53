"""Shared fixtures: the contract suite runs once per backend in CONTRACT_BACKENDS: the shipped
ones of BACKENDS, and `ref`, a test-only backend (tests/reference_backend.py: each world's own
MjData and mj_step) registered here as any backend outside batchsim would be, the proof that a
backend is one class and one registry line (issue 22).

`mjx-2dev` and `warp-2dev` are the multi-device path: every `batchsim.make(..., "mjx")`
(or "warp") of the module spreads its worlds over two CPU devices (JAX's, made two by
XLA_FLAGS below; Warp's one CPU device, twice), so the suite runs unchanged on it.
`warp-2proc` is the same with each device's share in a process of its own: set
BATCHSIM_SHARD_PROCESSES=1 to run the suite on it too (a process fleet costs seconds to
start on 2 cores, so CI runs tests/test_devices.py's process tests instead). On a host with
two GPUs, BATCHSIM_TEST_WARP_DEVICES=cuda:0,cuda:1 puts warp's two devices on them.

A backend whose optional packages are missing is skipped, unless
BATCHSIM_FORCE_BACKENDS=1 (CI sets it, so a broken install fails instead of skipping);
`need(module)` does the same for any optional package a test imports (rclpy, jax, ...).
"""

from __future__ import annotations

import functools
import importlib.util
import os
import tempfile
import types

# before JAX is imported anywhere: two CPU devices, for the multi-device tests
os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
# mjx compiles the same programs again and again across tests (a fresh system per test, the
# 2-device variants): JAX's persistent cache lets every test after the first load them
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", os.path.join(tempfile.gettempdir(), f"batchsim-jax-cache-{os.getuid()}"))

import pytest  # noqa: E402
from reference_backend import ReferenceEngine  # noqa: E402

import batchsim  # noqa: E402

batchsim.backends.register("ref", ReferenceEngine)  # a backend from outside batchsim: this one line

# backend -> the module its optional packages provide
BACKENDS = {"cpu": "mujoco", "mjx": "jax", "warp": "mujoco_warp", "mjx-2dev": "jax", "warp-2dev": "mujoco_warp"}
if os.environ.get("BATCHSIM_SHARD_PROCESSES") == "1":  # 5 minutes more on 2 cores: not in CI's run
    BACKENDS["warp-2proc"] = "mujoco_warp"
CONTRACT_BACKENDS = {**BACKENDS, "ref": "mujoco"}
TWO_DEVICES = {"mjx": ["cpu:0", "cpu:1"], "warp": ["cpu", "cpu"]}
if os.environ.get("BATCHSIM_TEST_WARP_DEVICES"):  # e.g. "cuda:0,cuda:1": warp-2dev/2proc on a GPU host's cards
    TWO_DEVICES["warp"] = os.environ["BATCHSIM_TEST_WARP_DEVICES"].split(",")


def _available(backend: str) -> bool:
    return importlib.util.find_spec(CONTRACT_BACKENDS[backend]) is not None


@pytest.fixture(params=list(CONTRACT_BACKENDS), scope="module")
def backend(request) -> str:
    """Every backend, the multi-device path of mjx and warp, and `ref`: for the contract suite."""
    yield from _backend(request.param)


@pytest.fixture(params=list(BACKENDS), scope="module")
def shipped_backend(request) -> str:
    """The shipped backends and the multi-device path of mjx and warp: for the suites of what the
    contract leaves to a backend to offer, which `ref` does not (cameras and lidars)."""
    yield from _backend(request.param)


@pytest.fixture(params=[b for b in BACKENDS if "-" not in b], scope="module")
def one_device_backend(request) -> str:
    """Every shipped backend on one device: for tests where the device count changes nothing."""
    yield from _backend(request.param)


def _backend(name: str):
    if not _available(name) and os.environ.get("BATCHSIM_FORCE_BACKENDS") != "1":
        pytest.skip(f"backend {name} needs {CONTRACT_BACKENDS[name]}, which is not installed")
    base, _, sharded = name.partition("-")
    if not sharded:
        yield name
        return
    make = batchsim.make

    @functools.wraps(make)
    def make_on_two_devices(model, nworld=1, backend="auto", **options):
        if backend == base and "devices" not in options and nworld >= 2:
            options["devices"] = TWO_DEVICES[base]
            options["processes"] = sharded == "2proc"
        return make(model, nworld, backend, **options)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(batchsim, "make", make_on_two_devices)
        yield base


def need(module: str, hint: str = "") -> types.ModuleType:
    """Import an optional package's `module` for a test, or at the top of a test file: where it
    does not import, skip, unless BATCHSIM_FORCE_BACKENDS=1 (CI), where the ImportError fails
    the test (or the whole file) instead. In place of `pytest.importorskip`, which never fails:
    tests/test_ci.py allows no other."""
    try:
        return importlib.import_module(module)
    except ImportError as error:
        if os.environ.get("BATCHSIM_FORCE_BACKENDS") == "1":
            raise
        why = f"{module} is not importable ({error})" + (f"; {hint}" if hint else "")
        pytest.skip(why, allow_module_level=True)


def fake_shm_free(monkeypatch, free: int) -> None:
    """/dev/shm reports `free` bytes free (of 64 MiB) to os.statvfs while the test runs."""
    import os

    real = os.statvfs

    def statvfs(path):
        st = real(path)
        if str(path) != "/dev/shm":
            return st
        return os.statvfs_result((st.f_bsize, 4096, 16384, free // 4096, free // 4096, *tuple(st)[5:]))

    monkeypatch.setattr(os, "statvfs", statvfs)
