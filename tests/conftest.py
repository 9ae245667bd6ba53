"""Shared fixtures: the contract suite runs once per backend in BACKENDS.

A backend whose optional packages are missing is skipped, unless
BATCHSIM_FORCE_BACKENDS=1 (CI sets it, so a broken install fails instead of skipping).
"""

from __future__ import annotations

import importlib.util
import os

import pytest

# backend -> the module its optional packages provide
BACKENDS = {"cpu": "mujoco", "mjx": "jax", "warp": "mujoco_warp"}


def _available(backend: str) -> bool:
    return importlib.util.find_spec(BACKENDS[backend]) is not None


@pytest.fixture(params=list(BACKENDS), scope="module")
def backend(request) -> str:
    name = request.param
    if not _available(name) and os.environ.get("BATCHSIM_FORCE_BACKENDS") != "1":
        pytest.skip(f"backend {name} needs {BACKENDS[name]}, which is not installed")
    return name
