"""The controller base class and the parameter reader (the manager lives in manager.py).

A controller is built from its ros2_control parameters and the robot's interfaces, and
from then on touches the simulation only through the hardware-interface contract: it
reads `sim.state` columns and writes `sim.command` columns, by interface name, resolved
once into index arrays. `update` runs once per control period for every world at once.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, ClassVar

import numpy as np

from batchsim.controllers.topics import ControllerTopics
from batchsim.model import RobotSpec
from batchsim.types import ConfigurationError, world_out_of_range

_MISSING = object()


class Params:
    """A controller's `ros__parameters`, flattened to dotted keys (`linear.x.max_velocity`).

    Every getter names the file, the controller and the key in the ConfigurationError it
    raises; `unused()` lists the keys nobody asked for, so that typos can be reported, and
    `warnings` holds the lines a controller writes about keys it read and ignores (a typo
    inside a block it reads whole), reported beside them.
    """

    def __init__(self, values: Mapping[str, Any], *, where: str, controller: str):
        self.values = dict(values)
        self.where = where
        self.controller = controller
        self.warnings: list[str] = []
        self._read: set[str] = set()

    def error(self, key: str, message: str) -> ConfigurationError:
        return ConfigurationError(f"{self.where}: controller {self.controller!r}: {key}: {message}")

    def has(self, key: str) -> bool:
        return key in self.values

    def keys_under(self, prefix: str) -> list[str]:
        """The keys that start with `prefix.`, marked as read."""
        keys = [k for k in self.values if k.startswith(prefix + ".")]
        self._read.update(keys)
        return keys

    def raw(self, key: str, default: Any = _MISSING) -> Any:
        self._read.add(key)
        if key in self.values:
            return self.values[key]
        if default is _MISSING:
            raise self.error(key, "missing (required)")
        return default

    def string_list(self, key: str, default: Any = _MISSING, *, nonempty: bool = False) -> list[str]:
        value = self.raw(key, default)
        if value is None:
            value = []
        if isinstance(value, str) or not isinstance(value, Sequence):
            raise self.error(key, f"must be a list of names, got {value!r}")
        if not all(isinstance(v, str) and v for v in value):
            raise self.error(key, f"must be a list of names, got {list(value)!r}")
        if nonempty and not value:
            raise self.error(key, "must name at least one entry")
        dup = sorted({v for v in value if list(value).count(v) > 1})
        if dup:
            raise self.error(key, f"{dup[0]!r} is listed twice")
        return list(value)

    def string(self, key: str, default: Any = _MISSING) -> str:
        value = self.raw(key, default)
        if not isinstance(value, str):
            raise self.error(key, f"must be a string, got {value!r}")
        return value

    def number(
        self,
        key: str,
        default: Any = _MISSING,
        *,
        minimum: float | None = None,
        positive: bool = False,
        allow_nan: bool = False,
    ) -> float:
        value = self.raw(key, default)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.error(key, f"must be a number, got {value!r}")
        value = float(value)
        if math.isnan(value):
            if allow_nan:
                return value
            raise self.error(key, "must be a number, got nan")
        if math.isinf(value):
            raise self.error(key, f"must be finite, got {value!r}")
        if positive and not value > 0:
            raise self.error(key, f"must be > 0, got {value:g}")
        if minimum is not None and value < minimum:
            raise self.error(key, f"must be >= {minimum:g}, got {value:g}")
        return value

    def boolean(self, key: str, default: Any = _MISSING) -> bool:
        value = self.raw(key, default)
        if not isinstance(value, bool):
            raise self.error(key, f"must be true or false, got {value!r}")
        return value

    def choice(self, key: str, choices: Sequence[str], default: Any = _MISSING) -> str:
        value = self.string(key, default)
        if value not in choices:
            raise self.error(key, f"must be one of {', '.join(choices)}, got {value!r}")
        return value

    def unused(self, accepted: Iterable[str] = ()) -> list[str]:
        """Keys never read and not under one of the `accepted` names or prefixes."""
        accepted = tuple(accepted)
        return sorted(
            k
            for k in self.values
            if k not in self._read and not any(k == a or k.startswith(a + ".") for a in accepted)
        )


class Controller:
    """One ros2_control controller over every world.

    Subclasses set TYPE (the plugin name the YAML's `type` gives), read their parameters
    in `__init__`, claim command interfaces through `claim()`, and implement `update`.

    Attributes:
      name: the controller's name in the YAML (its topics live under `<ns>/<name>/`).
      nworld: number of worlds.
      command_interfaces: the command interfaces it claims, `"<joint>/<interface>"`.
      state_interfaces: the state interfaces it reads.
    """

    TYPE: ClassVar[str] = ""
    #: stock parameters accepted for compatibility that batchsim does not act on
    ACCEPTED: ClassVar[tuple[str, ...]] = ("update_rate", "is_async")
    #: attributes that hold a frame id (the broadcasters' `frame_id`, the diff drive's two)
    FRAME_ATTRIBUTES: ClassVar[tuple[str, ...]] = ("frame_id", "odom_frame_id", "base_frame_id")

    def __init__(self, name: str, params: Params, spec: RobotSpec, nworld: int):
        self.name = name
        self.params = params
        self.spec = spec
        self.nworld = int(nworld)
        self.command_interfaces: list[str] = []
        self.state_interfaces: list[str] = []
        self._command_names = spec.command_interfaces
        self._state_names = spec.state_interfaces
        self.time = 0.0  # the loop time of the last update
        # the robot's namespace inside a world of several (`arm_a/`, batchsim.controllers.robots),
        # for topics ros2_control puts at the controller_manager's namespace: "" for a world of one
        self.namespace = ""

    def name_frames(self, robot_prefix: str = "") -> None:
        """Its frame ids as tf names them: `{ns}/<robot prefix><frame>`, the bridge putting the
        world's namespace for `{ns}` (`world_3/odom`, `world_3/amr_2/odom`; `odom` in a
        root-namespace world). A frame id that holds `{ns}` already stays as given."""
        for attr in self.FRAME_ATTRIBUTES:
            frame = getattr(self, attr, None)
            if isinstance(frame, str) and frame and "{ns}" not in frame:
                setattr(self, attr, f"{{ns}}/{robot_prefix}{frame}")

    # --- interface resolution, at configuration time ---
    def check_joints(self, key: str, joints: Sequence[str]) -> None:
        # a ros2_control joint may be an actuator's name (a tendon-driven gripper): it has commands
        known = {j.name for j in self.spec.joints} | {c.rsplit("/", 1)[0] for c in self._command_names}
        for j in joints:
            if j not in known:
                raise self.params.error(
                    key, f"the model has no joint {j!r} (joints: {', '.join(sorted(known)) or 'none'})"
                )

    def claim(self, key: str, names: Sequence[str]) -> np.ndarray:
        """Command columns for `names`, claimed by this controller; ConfigurationError if absent."""
        cols = []
        for n in names:
            if n not in self._command_names:
                joint = n.rsplit("/", 1)[0]
                served = [c.rsplit("/", 1)[1] for c in self._command_names if c.rsplit("/", 1)[0] == joint]
                have = f"{joint} has: {', '.join(served)}" if served else f"{joint} has none"
                raise self.params.error(key, f"the model has no command interface {n!r} ({have})")
            cols.append(self._command_names.index(n))
            self.command_interfaces.append(n)
        return np.array(cols, dtype=np.intp)

    def state_columns(self, key: str, names: Sequence[str]) -> np.ndarray:
        """State columns for `names`; ConfigurationError if the model lacks one."""
        cols = []
        for n in names:
            if n not in self._state_names:
                raise self.params.error(key, f"the model has no state interface {n!r}")
            cols.append(self._state_names.index(n))
            if n not in self.state_interfaces:
                self.state_interfaces.append(n)
        return np.array(cols, dtype=np.intp)

    # --- parameters at run time (its node's set_parameters) ---
    def runtime_parameters(self) -> dict[str, Any]:
        """The parameters it takes at run time, with their values at start (defaults included,
        as upstream's node declares them); none by default: a controller takes its parameters
        when the fleet starts."""
        return {}

    def set_parameters(self, worlds: np.ndarray, values: Mapping[str, Any]) -> str:
        """Set parameters (dotted keys, as its node names them) in the listed worlds, from the
        next update on: "" done, else one line saying why nothing changed."""
        key = next(iter(values), "")
        return f"controller {self.name!r}: cannot set {key!r} at run time: it takes its parameters at start (change the YAML and restart)"

    # --- the loop ---
    def activate(self, sim: Any, time: float) -> None:
        """First period: take the current state as the starting point (hold where the robot is).

        Inputs given before it (a trajectory, a command) are kept.
        """

    def reset(self, sim: Any, worlds: np.ndarray) -> None:
        """The listed worlds were reset: drop their goals and hold them where they are now."""

    def deactivate(self, sim: Any, worlds: np.ndarray) -> None:
        """The controller became inactive in the listed worlds (switch_controller): as a reset,
        but a goal in flight ends DEACTIVATED (upstream: "Current goal cancelled during
        deactivate transition."), not as if the world were reset."""
        self.reset(sim, worlds)

    def update(self, sim: Any, time: float, period: float) -> None:
        raise NotImplementedError

    def prepare(self, time: float) -> None:
        """Optional: work for the update at `time` done ahead, while the device steps the period
        before it (ControllerManager.while_stepping); from the controller's own state only, and
        none that update() would not redo if something changed meanwhile."""

    def topics(self) -> ControllerTopics:
        """The controller's per-world ROS topics, as data (batchsim/controllers/topics.py)."""
        return ControllerTopics(self.name)

    def _world(self, world: int) -> int:
        """The one world of a per-world call (`set_trajectory(world, ...)`), as an int;
        ValueError naming the controller for a world out of range or not whole."""
        if isinstance(world, bool) or int(world) != world or not 0 <= world < self.nworld:
            raise ValueError(world_out_of_range(world, self.nworld, self.name))
        return int(world)

    def _batch_worlds(self, worlds: Any) -> tuple[np.ndarray, dict[int, str]]:
        """(n,) world indices of a batched input, and {index: reason} for those out of range (set to 0).

        Not batchsim.types.worlds_index, deliberately: these are the worlds of n inputs, not a
        list of worlds. Each entry is judged alone (a bad one is refused with its reason, the
        others are applied), a world may come twice (the later input wins: last_per_world),
        and a float world is one more entry to judge (NaN or 2.5 refused, 2.0 taken)."""
        given = np.asarray(worlds).reshape(-1)
        if given.dtype.kind not in "iuf":
            raise ValueError(f"{self.name}: worlds must be integers, got {given.dtype}")
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(given) & (given == np.round(given)) & (given >= 0) & (given < self.nworld)
        rows = np.where(ok, given, 0).astype(np.int64)
        return rows, {int(k): world_out_of_range(given[k], self.nworld, self.name) for k in np.flatnonzero(~ok)}


def rows_all(x: np.ndarray) -> np.ndarray:
    """(n,) bool: every value of each row of the (n, k) bool `x` is true. A whole-array test
    first: a reduction along short rows is ten times slower, and usually every row passes."""
    return np.ones(len(x), bool) if x.all() else x.all(axis=1)



def rows_any(x: np.ndarray) -> np.ndarray:
    """(n,) bool: some value of each row of the (n, k) bool `x` is true (as rows_all: usually none)."""
    return x.any(axis=1) if x.any() else np.zeros(len(x), bool)


def ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The concatenation of arange(start, start + count) for each pair, (counts.sum(),) intp."""
    counts = np.asarray(counts, dtype=np.intp)
    ends = np.cumsum(counts)
    return np.arange(int(ends[-1]) if len(ends) else 0) + np.repeat(
        np.asarray(starts) - (ends - counts), counts
    )


def last_per_world(worlds: np.ndarray) -> np.ndarray:
    """Indices of the last entry for each distinct world, in increasing order: a later input wins."""
    if len(worlds) < 2 or (worlds[1:] > worlds[:-1]).all():  # each world once, in order: no sort
        return np.arange(len(worlds))
    _, first_from_end = np.unique(worlds[::-1], return_index=True)
    return np.sort(len(worlds) - 1 - first_from_end)
