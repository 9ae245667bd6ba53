"""The contract's shared types: return codes and status bits, the failure report a backend
gives, the sensor mapping and frames a user gets, the limits read() and write() use, and the
split of the worlds into contiguous ranges (over devices and over bridge workers alike).

Every batched array leads with the world: `nworld`, or `n`/`k` for the worlds a call lists;
each field's docstring gives its shape and dtype.
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Mapping, Sequence
from concurrent.futures import Future
from typing import Any, NamedTuple, Protocol

import numpy as np

# re-exported: they live in batchsim/basics.py, which needs no NumPy
from batchsim.basics import AnyCase as AnyCase
from batchsim.basics import ConfigurationError as ConfigurationError
from batchsim.basics import OptionError as OptionError


class _AddsNoise(Protocol):
    """What PendingFrames needs of the sensor suite (batchsim.sensors.SensorSuite)."""

    def add_noise(self, name: str, values: np.ndarray, worlds: np.ndarray) -> None: ...


class ReturnType(enum.Enum):
    """What read() and write() return (hardware_interface::return_type)."""

    OK = 0
    ERROR = 1
    DEACTIVATE = 2


class Status(enum.IntFlag):
    """Per-world status bits (`BatchedSystem.status`: (nworld,) uint8). One bad world never stops
    the others."""

    OK = 0
    DIVERGED = 1  # NaN/inf or a MuJoCo instability warning: frozen until reset
    OVERFLOW = 2  # contact or constraint buffer overflow: frozen until reset
    BAD_COMMAND = 4  # the last write's command for this world was rejected, not applied


#: the status bits that freeze a world until reset
FROZEN = Status.DIVERGED | Status.OVERFLOW
#: MuJoCo's mjMAXVAL: a ctrl beyond it trips mjWARN_BADCTRL; write() rejects a command beyond it
MAX_COMMAND = 1e10


class StateSource(enum.Enum):
    """The engine field a state interface is read from (`StateColumn.source`): the value is the
    MjData field's name; read() gathers them in the members' order."""

    QPOS = "qpos"
    QVEL = "qvel"
    QFRC_ACTUATOR = "qfrc_actuator"
    SENSORDATA = "sensordata"


#: the engine fields read() gathers state interfaces from, in StateSource's order
READ_FIELDS = tuple(s.value for s in StateSource)


def check_plugin_runs(plugin: Any, runs: bool, kind: str) -> None:
    """ConfigurationError naming the file and key of a mujoco_ros2_control plugin's params
    (`plugin.where`; None: not configured) that a system cannot run (`runs` False: a fleet
    spread over several devices, whose shards the plugin's per-world state does not reach)."""
    if plugin is not None and not runs:
        raise ConfigurationError(f"{plugin.where}: the {kind} is not run on a fleet spread over several devices: use one")


class SensorData(Mapping[str, np.ndarray]):
    """Every MJCF sensor by name: `sim.sensordata["wrist_force"]` is `(nworld, dim)`.

    Attributes:
      array: (nworld, nsensordata) float64, every sensor's values in MuJoCo's sensordata
        order; the named arrays are views of it.
    """

    def __init__(self, array: np.ndarray, sensors: Sequence[Any]):
        self.array = array
        self._views = {s.name: array[:, s.adr : s.adr + s.dim] for s in sensors}

    def __getitem__(self, name: str) -> np.ndarray:
        try:
            return self._views[name]
        except KeyError:
            raise KeyError(f"no sensor named {name!r}; sensors: {', '.join(self._views)}") from None

    def __iter__(self):
        return iter(self._views)

    def __len__(self) -> int:
        return len(self._views)


@dataclasses.dataclass
class StepFailures:
    """The worlds that failed during one `Engine.step` call, as an engine reports them.

    Attributes:
      worlds: (k,) int64, the worlds; none of them was frozen before the call.
      status: (k,) uint8, their Status bits: DIVERGED and/or OVERFLOW.
      reasons: k strings, why each failed (MuJoCo's warning text where there is one).
      readings: (k, ncolumn) float64, their read() columns (`state`, then `base_state`) as
        they were at the start of the call.
      sensordata: (k, nsensordata) float64, likewise.
      time: (k,) float64, likewise.
      finished: whether `readings` are finished as read() shows them (taken from the `start`
        the contract handed the engine), else a raw gather the contract finishes.
    """

    worlds: np.ndarray
    status: np.ndarray
    reasons: list[str]
    readings: np.ndarray
    sensordata: np.ndarray
    time: np.ndarray
    finished: bool = False


@dataclasses.dataclass(frozen=True)
class HeldBase:
    """The free joint whose planar velocity the BaseVelocityPlugin holds (batchsim.plugins): its
    qpos address (7 entries) and its dof address (6)."""

    qposadr: int
    dofadr: int


class Frames(NamedTuple):
    """What `render` returns, row i for the i-th world asked for.

    Attributes:
      rgb: (n, H, W, 3) uint8, top row first; with `device=True` (nworld, H, W, 3), the
        backend's own array type.
      depth: (n, H, W) float32, metres along the optical axis; +inf where nothing was hit, NaN
        where noise dropped a pixel.
    """

    rgb: Any
    depth: Any


class PendingFrames:
    """Frames being rendered (`BatchedSystem.render_async`): `result()` waits for them.

    Attributes:
      camera: the camera's name.
      worlds: (n,) the worlds, in the order asked for, as `render` orders them.
    """

    def __init__(
        self,
        future: Future,
        camera: str,
        worlds: np.ndarray,
        suite: _AddsNoise,
        order: np.ndarray | None = None,
    ):
        self.camera = camera
        self.worlds = worlds
        self._future = future
        self._suite = suite
        self._order = order  # the future's rows (ascending worlds) -> the worlds' order; None: already
        self._frames: Frames | None = None

    def done(self) -> bool:
        """True once `result()` would not wait."""
        return self._frames is not None or self._future.done()

    def result(self) -> Frames:
        """Frames(rgb (n, H, W, 3) uint8, depth (n, H, W) float32), the caller's own arrays, as
        `render(camera, worlds)` returned at the call; depth noise is drawn here, the first time.
        Re-raises what the render raised."""
        if self._frames is None:
            rgb, depth = self._future.result()
            if self._order is not None:
                rgb, depth = rgb[self._order], depth[self._order]
            self._suite.add_noise(self.camera, depth, self.worlds)
            self._frames = Frames(rgb, depth)
        return self._frames


def check_nstep(nstep: Any) -> None:
    """A step count: a whole number >= 1 (`step(2.5)` once ran 2 steps). ValueError otherwise."""
    if isinstance(nstep, bool) or not isinstance(nstep, int | np.integer) or nstep < 1:
        raise ValueError(f"nstep must be a whole number of physics steps >= 1, got {nstep!r}")


def world_out_of_range(world: Any, nworld: int, what: str = "") -> str:
    """The message for a world index not in 0..nworld - 1, led by `what: ` when given (the
    controller's name): worlds_index's, and a controller's for one world or one entry of a
    batched input."""
    if isinstance(world, np.generic):  # 4, not np.int64(4)
        world = world.item()
    return f"{what + ': ' if what else ''}world {world!r} is out of range: worlds are 0..{nworld - 1}"


def worlds_index(worlds: Sequence[int] | np.ndarray | int | None, nworld: int, *, what: str = "") -> np.ndarray | None:
    """The worlds a call lists (`worlds=` of the contract, SimLoop.reset, switch_controller)
    as (k,) int64 indices in the caller's order; None for None (every world).

    `worlds` is integers (a sequence, an array of any shape, or one), or a (nworld,) bool mask
    (its True worlds, in world order). ValueError, led by `what: ` when given, for a mask of
    another shape, values that are not integers (1.5, and 2.0 too), a world out of range, or a
    world listed twice.
    """
    if worlds is None:
        return None
    rows = np.asarray(worlds)
    lead = f"{what}: " if what else ""
    if rows.dtype == bool:
        if rows.shape != (nworld,):
            raise ValueError(f"{lead}a world mask must have shape ({nworld},), got {rows.shape}")
        return np.flatnonzero(rows)
    if rows.size and not np.issubdtype(rows.dtype, np.integer):
        raise ValueError(f"{lead}worlds must be integers or a ({nworld},) bool mask, got {rows.dtype}")
    rows = rows.astype(np.int64).reshape(-1)
    bad = rows[(rows < 0) | (rows >= nworld)]
    if bad.size:
        raise ValueError(world_out_of_range(bad[0], nworld, what))
    if rows.size > 1:
        unique, counts = np.unique(rows, return_counts=True)
        if unique.size < rows.size:
            raise ValueError(f"{lead}world {unique[counts > 1][0]} is listed more than once")
    return rows


def split_worlds(nworld: int, parts: int) -> list[range]:
    """`parts` contiguous ranges of `nworld` worlds, as even as can be (sizes differ by one at
    most): range i ends at world round(nworld * (i + 1) / parts), halves rounded up.
    ValueError unless 1 <= parts <= nworld."""
    if not 1 <= parts <= nworld:
        raise ValueError(f"{nworld} worlds cannot be split into {parts} ranges")
    edges = [(2 * i * nworld + parts) // (2 * parts) for i in range(parts + 1)]
    return [range(lo, hi) for lo, hi in zip(edges[:-1], edges[1:], strict=True)]


def as_slice(index: Sequence[int] | np.ndarray) -> slice | np.ndarray:
    """Indices that step evenly upward as the equal slice (a copy through a slice skips the gather
    an index array makes: half the time at (4096, 6) of a (4096, 36) array), else as an index
    array."""
    index = np.asarray(index, dtype=np.intp).reshape(-1)
    if len(index) == 0 or index[0] < 0:
        return index
    step = int(index[1] - index[0]) if len(index) > 1 else 1
    if step < 1 or (np.diff(index) != step).any():
        return index
    return slice(int(index[0]), int(index[-1]) + 1, step)
