"""Backends: one class each, registered by name. `resolve()` picks one for `auto`.

A new backend is one module here with a `BatchedSystem` subclass, plus one line in
`_REGISTRY`; it is done when the contract suite in tests/ passes on it unchanged.
"""

from __future__ import annotations

import enum
import importlib
import os
from pathlib import Path

from batchsim.hardware import BatchedSystem, ConfigurationError
from batchsim.loop import OptionError
from batchsim.model import RobotSpec
from batchsim.startup import install_command


class Backend(enum.Enum):
    """Where the worlds run. Strings are accepted case-insensitively at the edges."""

    AUTO = "auto"
    CPU = "cpu"
    MJX = "mjx"
    WARP = "warp"

    @classmethod
    def parse(cls, value: str | Backend) -> Backend:
        if isinstance(value, Backend):
            return value
        try:
            return cls(str(value).lower())
        except ValueError:
            names = ", ".join(b.value for b in cls)
            raise OptionError("", f"unknown backend {value!r} (choose from {names})") from None


# backend -> (module, class, the pip extra that brings its packages)
_REGISTRY: dict[Backend, tuple[str, str, str | None]] = {
    Backend.CPU: ("batchsim.backends.cpu", "CpuSystem", None),
    Backend.MJX: ("batchsim.backends.mjx", "MjxSystem", "mjx"),
    Backend.WARP: ("batchsim.backends.warp", "WarpSystem", "warp"),
}

# auto: on a CUDA GPU, warp from this many worlds up, cpu below. The crossover of the two
# backends' contract throughput, measured with the humanoid on a 16-core H200 host by
# benchmarks/throughput.py --around-threshold (benchmarks/RESULTS.md, "Held out"): cpu
# faster at 128 worlds, warp at 256.
WARP_MIN_WORLDS = 256


class BackendUnavailable(ImportError):
    """A backend whose optional packages are not installed."""


def backend_class(backend: Backend) -> type[BatchedSystem]:
    """The class of a concrete backend, importing its heavy packages only now."""
    if backend not in _REGISTRY:
        raise OptionError("", f"backend {backend.value!r} is not available in this version of batchsim")
    module, cls, extra = _REGISTRY[backend]
    try:
        return getattr(importlib.import_module(module), cls)
    except ImportError as e:
        hint = f": {install_command(extra)}" if extra else ""
        raise BackendUnavailable(
            f"backend {backend.value!r} needs the package {e.name!r}, which is not installed{hint}"
        ) from None


class UnsupportedModel(ConfigurationError):
    """A model feature that the chosen backend cannot simulate."""


def unsupported_error(backend: str, spec: RobotSpec, feature: str) -> UnsupportedModel:
    """The error a backend raises from its constructor (so from make()) for a model it cannot run."""
    can = ["cpu"]
    for other in (Backend.MJX, Backend.WARP):
        if other.value != backend and _supports(other, spec):
            can.append(other.value)
    return UnsupportedModel(
        f"{spec.name}: the {backend} backend cannot simulate this model ({feature}); "
        f"backends that can: {', '.join(can)}"
    )


def _supports(backend: Backend, spec: RobotSpec) -> bool:
    try:
        cls = backend_class(backend)
    except BackendUnavailable:
        return False
    check = getattr(cls, "unsupported", None)
    return check is None or check(spec) is None


def cuda_gpu() -> bool:
    """Whether this machine has an NVIDIA GPU that CUDA may use, without importing any GPU package."""
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None and visible.strip() in ("", "-1"):
        return False
    gpus = Path("/proc/driver/nvidia/gpus")
    return (gpus.is_dir() and any(gpus.iterdir())) or Path("/dev/nvidia0").exists()


def resolve(backend: str | Backend, spec: RobotSpec, nworld: int) -> tuple[Backend, str]:
    """The concrete backend for a request, and the reason it was chosen.

    `auto` keeps cpu on a machine without a CUDA GPU (JAX's and Warp's CPU devices are
    slower than mujoco.batch), and on one with a GPU picks warp from WARP_MIN_WORLDS worlds
    up, where it overtakes cpu in benchmarks/RESULTS.md.
    """
    choice = Backend.parse(backend)
    if choice is not Backend.AUTO:
        return choice, "requested"
    if not cuda_gpu():
        return Backend.CPU, "auto: no CUDA GPU, so mujoco.batch on the CPU"
    if nworld < WARP_MIN_WORLDS:
        return Backend.CPU, f"auto: {nworld} worlds, below the {WARP_MIN_WORLDS} where warp overtakes cpu"
    try:
        cls = backend_class(Backend.WARP)
    except BackendUnavailable:
        return Backend.CPU, f"auto: a CUDA GPU, but MuJoCo Warp is not installed ({install_command('warp')})"
    feature = cls.unsupported(spec)
    if feature is not None:
        return Backend.CPU, f"auto: MuJoCo Warp cannot simulate this model ({feature})"
    return Backend.WARP, f"auto: {nworld} worlds on a CUDA GPU, at or above the {WARP_MIN_WORLDS} where warp overtakes cpu"
