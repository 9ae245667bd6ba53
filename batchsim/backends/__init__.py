"""Backends: one class each, registered by name. `resolve()` picks one for `auto`.

A new backend is one module here with a `BatchedSystem` subclass, plus one line in
`_REGISTRY`; it is done when the contract suite in tests/ passes on it unchanged.
"""

from __future__ import annotations

import enum
import importlib

from batchsim.hardware import BatchedSystem
from batchsim.model import RobotSpec


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
            raise ValueError(f"unknown backend {value!r} (choose from {names})") from None


# backend -> (module, class, the pip extra that brings its packages)
_REGISTRY: dict[Backend, tuple[str, str, str | None]] = {
    Backend.CPU: ("batchsim.backends.cpu", "CpuSystem", None),
}


class BackendUnavailable(ImportError):
    """A backend whose optional packages are not installed."""


def backend_class(backend: Backend) -> type[BatchedSystem]:
    """The class of a concrete backend, importing its heavy packages only now."""
    if backend not in _REGISTRY:
        raise ValueError(f"backend {backend.value!r} is not available in this version of batchsim")
    module, cls, extra = _REGISTRY[backend]
    try:
        return getattr(importlib.import_module(module), cls)
    except ImportError as e:
        hint = f": pip install 'batchsim[{extra}]'" if extra else ""
        raise BackendUnavailable(
            f"backend {backend.value!r} needs the package {e.name!r}, which is not installed{hint}"
        ) from None


def resolve(backend: str | Backend, spec: RobotSpec, nworld: int) -> tuple[Backend, str]:
    """The concrete backend for a request, and the reason it was chosen."""
    choice = Backend.parse(backend)
    if choice is not Backend.AUTO:
        return choice, "requested"
    return Backend.CPU, "auto: mujoco.batch on the CPU"
