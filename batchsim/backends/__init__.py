"""Backends: one engine class each (batchsim.engine.Engine), registered by name; `resolve()`
picks one for `auto`. The contract (batchsim.hardware.BatchedSystem) owns the engine `make()`
builds; engines never import the contract.

A new backend is one module here with an Engine subclass, plus one line in `_REGISTRY`; it is
done when the contract suite in tests/ passes on it unchanged. An engine that lives outside
batchsim is one class and one `register("name", TheEngine)` call.

The class states what it can do; nothing outside this package asks for a backend by name:
`compiles_first_period`, `sensors_batched`, `reads_torque_sensors`, `device_dtype`, `OPTIONS`
(batchsim.engine), `available_devices()` and `device_memory(device)` (static methods,
where it runs on devices: mjx, warp),
`unsupported(spec)` (a classmethod: why it cannot simulate a model, or None) and
`physics_memory(m, nthread=, nconmax=, njmax=)` (a static method: what its physics takes,
batchsim.startup.PhysicsMemory; `physics_memory` below).
"""

from __future__ import annotations

import dataclasses
import enum
import importlib
import os
from pathlib import Path

import mujoco

from batchsim.engine import Engine
from batchsim.model import RobotSpec
from batchsim.startup import MemoryEstimate, PhysicsMemory, fleet_memory, install_command
from batchsim.types import AnyCase, ConfigurationError, OptionError


class Backend(AnyCase, enum.Enum):
    """The shipped backends, by name in any case; `parse` also takes the names given to `register`."""

    AUTO = "auto"
    CPU = "cpu"
    MJX = "mjx"
    WARP = "warp"

    @classmethod
    def parse(cls, value: str | Backend | Registered) -> Backend | Registered:
        """Any backend by name (a registered one as its `Registered`): the module's `parse`."""
        return parse(value)


@dataclasses.dataclass(frozen=True)
class Registered:
    """A backend made known with `register`, beside the shipped ones of `Backend`.

    Attributes:
      value: its name, lower case (as a `Backend` member's value).
      cls: its Engine subclass, whose `name` is `value`.
      extra: the pip extra that brings its packages, as the shipped registry lines name theirs;
        None: none.
    """

    value: str
    cls: type[Engine]
    extra: str | None = None


#: a concrete backend or `auto`: what `parse` and `resolve` return
Choice = Backend | Registered

# backend -> (module, class, the pip extra that brings its packages)
_REGISTRY: dict[Backend, tuple[str, str, str | None]] = {
    Backend.CPU: ("batchsim.backends.cpu", "CpuEngine", None),
    Backend.MJX: ("batchsim.backends.mjx", "MjxEngine", "mjx"),
    Backend.WARP: ("batchsim.backends.warp", "WarpEngine", "warp"),
}
# name -> backend, for those made known with register(), in the order they were
_REGISTERED: dict[str, Registered] = {}

# auto: on a CUDA GPU, warp from this many worlds up, cpu below. The crossover of the two
# backends' contract throughput, measured with the humanoid on a 16-core H200 host by
# benchmarks/throughput.py --around-threshold (benchmarks/RESULTS.md, "Held out"): cpu
# faster at 128 worlds, warp at 256.
WARP_MIN_WORLDS = 256


class BackendUnavailable(ImportError):
    """A backend whose optional packages are not installed."""


def register(name: str, cls: type[Engine], extra: str | None = None) -> None:
    """Make `cls` a backend: `batchsim.make(model, n, name)`, the command line's `--backend
    name` (in this process) and `resolve` take `name` from now on, and the choices an unknown
    name is told list it.

    Args:
      name: the backend's name, any case; it must be `cls.name` (the name its log lines and
        messages give) and not a shipped backend's or `auto`.
      cls: an Engine subclass (batchsim.engine) stating its capabilities (this package's
        docstring); done when the contract suite
        (tests/test_contract.py) passes on it unchanged.
      extra: the pip extra that brings its packages, if any, as the shipped ones name theirs.

    Raises:
      ValueError: a name that is taken or not the class's own, or a class that is not an
        Engine. Registering the same class under its name again changes nothing.
    """
    key = str(name).lower()
    if not (isinstance(cls, type) and issubclass(cls, Engine)):
        raise ValueError(f"backend {name!r}: {cls!r} is not a batchsim.engine.Engine subclass")
    if key in (b.value for b in Backend):
        raise ValueError(f"backend {name!r} is one of batchsim's own: register another name")
    if cls.name != key:
        raise ValueError(f"backend {name!r}: {cls.__name__}.name is {cls.name!r}; it must be the name registered")
    given = _REGISTERED.get(key)
    if given is not None and given.cls is not cls:
        raise ValueError(f"backend {name!r} is registered already, as {given.cls.__qualname__}")
    _REGISTERED[key] = Registered(key, cls, extra)


def names() -> list[str]:
    """Every backend's name: `auto`, the shipped ones, then the registered ones."""
    return [b.value for b in Backend] + list(_REGISTERED)


def parse(value: str | Choice) -> Choice:
    """A backend by name, any case (a Backend or Registered as it is); OptionError naming the
    choices otherwise."""
    if isinstance(value, Backend | Registered):
        return value
    try:
        return Backend(str(value))
    except ValueError:
        pass
    key = str(value).lower()  # register() keeps names in lower case
    if key in _REGISTERED:
        return _REGISTERED[key]
    raise OptionError("", f"unknown backend {value!r} (choose from {', '.join(names())})") from None


def backend_class(backend: Choice) -> type[Engine]:
    """The engine class of a concrete backend, importing its heavy packages only now."""
    if isinstance(backend, Registered):
        return backend.cls
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


def _concrete() -> list[Choice]:
    return [b for b in Backend if b is not Backend.AUTO] + list(_REGISTERED.values())


class UnsupportedModel(ConfigurationError):
    """A model feature that the chosen backend cannot simulate."""


def unsupported_error(backend: str, spec: RobotSpec, feature: str) -> UnsupportedModel:
    """The error an engine raises from its constructor (so from make()) for a model it cannot run."""
    can = [other.value for other in _concrete() if other.value != backend and _supports(other, spec)]
    return UnsupportedModel(
        f"{spec.name}: the {backend} backend cannot simulate this model ({feature}); "
        f"backends that can: {', '.join(can)}"
    )


def _supports(backend: Choice, spec: RobotSpec) -> bool:
    try:
        cls = backend_class(backend)
    except BackendUnavailable:
        return False
    check = getattr(cls, "unsupported", None)
    return check is None or check(spec) is None


def varying_backends(field: str, m: mujoco.MjModel) -> list[str]:
    """The installed backends that can give `field` per-world values (batchsim.variation.worlds)."""
    return [
        b.value
        for b in _concrete()
        if _installed(b) and field in backend_class(b).variable_fields(m)
    ]


def _installed(backend: Choice) -> bool:
    try:
        backend_class(backend)
    except BackendUnavailable:
        return False
    return True


# --- what a backend's worlds take (batchsim.startup does the sums) ---

def physics_memory(
    backend: Choice,
    m: mujoco.MjModel,
    *,
    nthread: int | None = None,
    nconmax: int | None = None,
    njmax: int | None = None,
) -> PhysicsMemory | None:
    """What a world of `m` takes on `backend`, as its class states it (`physics_memory`); None
    where it states nothing (the memory check is then skipped, and said so)."""
    state = getattr(backend_class(backend), "physics_memory", None)
    return None if state is None else state(m, nthread=nthread, nconmax=nconmax, njmax=njmax)


def estimate_memory(
    spec: RobotSpec,
    backend: str | Choice,
    nworld: int,
    *,
    ros: bool,
    nthread: int | None = None,
    on_device: bool = False,
    nconmax: int | None = None,
    njmax: int | None = None,
    controllers: bool = False,
    ros_workers: int = 1,
) -> MemoryEstimate | None:
    """What `nworld` worlds of `spec` on `backend` will take (batchsim.startup.fleet_memory);
    None for a backend that states no `physics_memory`.

    Args:
      ros: the ROS 2 bridge runs, in `ros_workers` worker processes.
      nthread: cpu: worker threads (None: every core).
      on_device: the backend runs on a GPU: its physics counts against device memory.
      nconmax, njmax: warp's contacts and constraint rows per world (None: not known yet).
      controllers: ros2_control-style controllers run in every world.
    """
    choice = parse(backend)
    physics = physics_memory(choice, spec.mjmodel, nthread=nthread, nconmax=nconmax, njmax=njmax)
    if physics is None:
        return None
    return fleet_memory(
        spec, choice.value, nworld, physics, ros=ros, on_device=on_device, controllers=controllers, ros_workers=ros_workers
    )


# --- auto ---


def cuda_gpu() -> bool:
    """Whether this machine has an NVIDIA GPU that CUDA may use, without importing any GPU package."""
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None and visible.strip() in ("", "-1"):
        return False
    gpus = Path("/proc/driver/nvidia/gpus")
    return (gpus.is_dir() and any(gpus.iterdir())) or Path("/dev/nvidia0").exists()


def resolve(backend: str | Choice, spec: RobotSpec, nworld: int) -> tuple[Choice, str]:
    """The concrete backend for a request, and the reason it was chosen.

    `auto` keeps cpu on a machine without a CUDA GPU (JAX's and Warp's CPU devices are
    slower than mujoco.batch), and on one with a GPU picks warp from WARP_MIN_WORLDS worlds
    up, where it overtakes cpu in benchmarks/RESULTS.md. A registered backend is only ever
    the one asked for.
    """
    choice = parse(backend)
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
