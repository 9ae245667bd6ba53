"""joint_trajectory_controller/JointTrajectoryController, over every world at once.

Semantics follow ros2_control's controller:

- A trajectory (trajectory_msgs/JointTrajectory) starts at its header stamp in sim time,
  or at the next update if the stamp is zero. Its points are timed from that start by
  their `time_from_start`, which must be strictly increasing.
- When it starts, the controller inserts the current state (measured position and, if
  the state interfaces have it, velocity; the last reference instead with
  `open_loop_control`) as the point the first segment leaves from.
- Interpolation (`interpolation_method: splines`, the default): linear between points
  that give positions only, cubic where they give velocities too, quintic where they give
  accelerations as well (ros2_control's Trajectory Representation). `none` holds each
  point until the next one's time.
- After the last point the reference holds that point, with zero velocity.
- A new trajectory replaces the current one from its own start time: until then the old
  one keeps running; points already in the past at that time are dropped. A trajectory
  with no points stops the world where it is. A newer trajectory replaces one still
  waiting to start.
- Joints a partial goal (`allow_partial_joints_goal`) leaves out hold their reference.
- Rejected, with a reason and the world unchanged: unknown joints, missing joints unless
  `allow_partial_joints_goal`, non-increasing or negative times, mismatched or non-finite
  values, a trajectory that ends before it would start, more points than
  `max_trajectory_points` (a batchsim parameter, default 10,000), and any value or
  spline between points that would command MAX_COMMAND (1e10) or more, which write()
  would refuse (the check covers what the claimed interfaces get: the position, velocity
  or acceleration reference, or the PID's output from them; the first segment is checked
  as though it left from rest, since the state it leaves from is known only at the start).
  Positions beyond a joint's range are accepted, as upstream accepts them: the actuator's
  ctrlrange and the joint's limit stop the joint, as on a real robot.

At fleet scale trajectories arrive as a `TrajectoryBatch`, one call per period however
many messages came: validation, queueing and the start of every due trajectory are
vectorized over the batch. Points live in one flat pool of segment rows (each row: a
segment's time and its polynomial), a block per world and trajectory, so memory follows
each world's own trajectory; each world keeps the index of its current segment, which
advances as time does, so sampling costs O(worlds), not O(points).

Commands: a `position` interface gets the reference position (and `velocity`, when
claimed alongside it, the reference velocity); a lone `velocity` or `effort` interface
gets `ff_velocity_scale * v_ref + PID(error)` with `gains.<joint>.p/i/d/i_clamp/
ff_velocity_scale`, as the stock controller computes it.
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np

from batchsim.controllers.base import Controller, Params, last_per_world, ranges
from batchsim.controllers.topics import ControllerTopics, Input, MessageKind, Output, TrajectoryBatch
from batchsim.hardware import MAX_COMMAND
from batchsim.model import RobotSpec

# the combinations of command interfaces the stock controller accepts
COMMAND_COMBINATIONS = (
    ("position",),
    ("velocity",),
    ("effort",),
    ("position", "velocity"),
    ("position", "velocity", "acceleration"),
)
STATE_COMBINATIONS = (("position",), ("position", "velocity"), ("position", "velocity", "acceleration"))
DEFAULT_MAX_POINTS = 10_000


class Spline(enum.IntEnum):
    """How a trajectory's segments interpolate, from what its points give."""

    LINEAR = 1  # positions only
    CUBIC = 2  # and velocities
    QUINTIC = 3  # and accelerations


_LINEAR, _CUBIC, _QUINTIC = (int(s) for s in Spline)  # as stored in int8 arrays


class Interpolation(enum.Enum):
    """The `interpolation_method` parameter."""

    SPLINES = "splines"
    NONE = "none"


# the blocks of pool rows a world may hold: rows of _SegmentPool.offset and .size
_RUNNING = 0  # the trajectory being followed
_PENDING = 1  # the one waiting for its start time
_SPARE = 2  # a released block, kept for the world's next trajectory
SPARE_ROWS = 64  # a spare up to this many rows stays with its world until it is reused
MIN_POOL_ROWS = 256

_D1 = np.arange(1.0, 6.0)  # d/ds s^k = k s^(k-1), k = 1..5
_D2 = np.array([2.0, 6.0, 12.0, 20.0])  # d2/ds2 s^k = k (k-1) s^(k-2), k = 2..5
_HOLD = np.array([[1.0, 0, 0, 0, 0, 0], [0] * 6, [0] * 6])  # past the last point: p = c0, at rest


class _SegmentPool:
    """Every world's trajectory rows in one flat array, a block of contiguous rows per trajectory.

    Row r of a block is point r's segment: `times[r]` its time from the trajectory's start
    and `coefficients[r]` the polynomial of the segment that leaves it. Blocks are carved
    from the end of the used rows. A released block becomes its world's spare, reused by
    its next trajectory if that needs between half of it and all of it (or it is small), so
    a fleet streaming trajectories reuses rows instead of allocating; a spare larger than
    SPARE_ROWS is freed when it does not fit that way, or when the world's trajectory ends.
    When the end of the array is reached, or fewer than a quarter of its rows are held, the
    held blocks are copied into a right-sized array.

    Attributes:
      times: (capacity,) float64.
      coefficients: (capacity, 6, njoint) float64, of s^0 .. s^5.
      offset: (3, nworld) int64, the first row of each world's running, pending and spare
        block, -1 for none.
      size: (3, nworld) int64, the rows each of those blocks holds.
      held: rows in blocks some world holds.
    """

    def __init__(self, nworld: int, njoint: int):
        self.njoint = njoint
        self.times = np.zeros(0)
        self.coefficients = np.zeros((0, 6, njoint))
        self.offset = np.full((3, nworld), -1, np.int64)
        self.size = np.zeros((3, nworld), np.int64)
        self.held = 0
        self.used = 0  # rows handed out from the start of the array, held or not

    @property
    def capacity(self) -> int:
        return len(self.times)

    def release(self, kind: int, worlds: np.ndarray) -> None:
        """Give up the `kind` blocks of `worlds` (each listed once): each becomes its world's
        spare if larger than the one it has (which is then freed), or is freed."""
        held = self.offset[kind, worlds] >= 0
        if not held.all():
            worlds = worlds[held]
            if not worlds.size:
                return
        off, size = self.offset[kind, worlds], self.size[kind, worlds]
        self.offset[kind, worlds] = -1
        self.size[kind, worlds] = 0
        keep = size > self.size[_SPARE, worlds]
        kept = worlds[keep]
        self.held -= int(size[~keep].sum()) + int(self.size[_SPARE, kept].sum())
        self.offset[_SPARE, kept] = off[keep]
        self.size[_SPARE, kept] = size[keep]

    def trim(self, worlds: np.ndarray, rows: np.ndarray | int = 0) -> None:
        """Free the spares of `worlds` larger than SPARE_ROWS and than twice `rows` (the size of
        the trajectory each world now has): memory follows the trajectories."""
        size = self.size[_SPARE, worlds]
        if not size.size or size.max() <= SPARE_ROWS:  # the usual case: nothing to free
            return
        large = worlds[(size > SPARE_ROWS) & (size > 2 * np.asarray(rows))]
        self.held -= int(self.size[_SPARE, large].sum())
        self.offset[_SPARE, large] = -1
        self.size[_SPARE, large] = 0

    def promote(self, worlds: np.ndarray) -> None:
        """The pending blocks of `worlds` become their running ones; the running ones are released."""
        self.release(_RUNNING, worlds)
        self.offset[_RUNNING, worlds] = self.offset[_PENDING, worlds]
        self.size[_RUNNING, worlds] = self.size[_PENDING, worlds]
        self.offset[_PENDING, worlds] = -1
        self.size[_PENDING, worlds] = 0
        self.trim(worlds, self.size[_RUNNING, worlds])  # a large block replaced by a small one goes

    def allocate(self, kind: int, worlds: np.ndarray, rows: np.ndarray) -> None:
        """Blocks of `rows` rows for `worlds` (each listed once, with no `kind` block yet)."""
        self.trim(worlds, rows)  # a large spare the new trajectory would not half fill goes
        fits = self.size[_SPARE, worlds] >= rows
        reuse = worlds[fits]
        self.offset[kind, reuse] = self.offset[_SPARE, reuse]
        self.size[kind, reuse] = self.size[_SPARE, reuse]
        self.offset[_SPARE, reuse] = -1
        self.size[_SPARE, reuse] = 0
        if len(reuse) == len(worlds):  # the usual case, streaming: every spare served
            return
        new, need = worlds[~fits], rows[~fits]
        total = int(need.sum())
        if not total:
            return
        if self.used + total > self.capacity:
            self._compact(total)
        self.offset[kind, new] = self.used + np.cumsum(need) - need
        self.size[kind, new] = need
        self.used += total
        self.held += total

    def shrink(self) -> None:
        """Copy the held blocks into a smaller array when most rows are no longer held."""
        if self.capacity > MIN_POOL_ROWS and self.held < self.capacity // 4:
            self._compact(0)

    def _compact(self, extra: int) -> None:
        kinds, worlds = np.nonzero(self.offset >= 0)
        off, size = self.offset[kinds, worlds], self.size[kinds, worlds]
        total = int(size.sum())
        capacity = max(MIN_POOL_ROWS, 2 * (total + extra))  # room for as much again before the next copy
        times = np.zeros(capacity)
        coefficients = np.zeros((capacity, 6, self.njoint))
        source = ranges(off, size)
        times[:total] = self.times[source]
        coefficients[:total] = self.coefficients[source]
        self.offset[kinds, worlds] = np.cumsum(size) - size
        self.times, self.coefficients = times, coefficients
        self.used = self.held = total


class JointTrajectoryController(Controller):
    """joint_trajectory_controller/JointTrajectoryController.

    Parameters (stock): `joints`, `command_joints`, `command_interfaces`,
    `state_interfaces`, `allow_partial_joints_goal`, `open_loop_control`,
    `interpolation_method` (splines, none), `gains.<joint>.{p, i, d, i_clamp,
    ff_velocity_scale}`; `constraints.*`, `action_monitor_rate`, `state_publish_rate` and
    the rest are accepted and not acted on. batchsim's own: `max_trajectory_points`
    (default 10,000), the most points a trajectory may have.

    Attributes (all (nworld, njoint), refreshed every update):
      reference_position, reference_velocity, reference_acceleration: the sampled trajectory.
      feedback_position, feedback_velocity: the measured state.
      error_position, error_velocity: reference minus feedback.
      output: the values written to the command interfaces, (nworld, ncommand).
      executing: (nworld,) bool, a trajectory is running and not yet past its last point.
    """

    TYPE: ClassVar[str] = "joint_trajectory_controller/JointTrajectoryController"
    ACCEPTED = (
        *Controller.ACCEPTED,
        "constraints",
        "action_monitor_rate",
        "state_publish_rate",
        "allow_integration_in_goal_trajectories",
        "allow_nonzero_velocity_at_trajectory_end",
        "cmd_timeout",
        "set_last_command_interface_value_as_state_on_activation",
        "angle_wraparound",
        "start_with_holding",
        "open_loop_control_reset",
        "speed_scaling",
        "interpolate_from_desired_state",
    )

    def __init__(self, name: str, params: Params, spec: RobotSpec, nworld: int):
        super().__init__(name, params, spec, nworld)
        self.joints = params.string_list("joints", nonempty=True)
        self.check_joints("joints", self.joints)
        command_joints = params.string_list("command_joints", []) or self.joints
        self.check_joints("command_joints", command_joints)
        if len(command_joints) != len(self.joints):
            raise params.error("command_joints", f"must name as many joints as joints ({len(self.joints)})")
        self.command_kinds = tuple(params.string_list("command_interfaces", nonempty=True))
        if tuple(sorted(self.command_kinds, key=_order)) not in COMMAND_COMBINATIONS:
            raise params.error(
                "command_interfaces",
                f"{list(self.command_kinds)} is not a combination the "
                f"controller supports ({'; '.join(map(str, map(list, COMMAND_COMBINATIONS)))})",
            )
        self.state_kinds = tuple(params.string_list("state_interfaces", nonempty=True))
        if tuple(sorted(self.state_kinds, key=_order)) not in STATE_COMBINATIONS:
            raise params.error(
                "state_interfaces",
                f"{list(self.state_kinds)} is not a combination the "
                f"controller supports ({'; '.join(map(str, map(list, STATE_COMBINATIONS)))})",
            )
        self.allow_partial = params.boolean("allow_partial_joints_goal", False)
        self.open_loop = params.boolean("open_loop_control", False)
        self.interpolation = Interpolation(
            params.choice("interpolation_method", [i.value for i in Interpolation], "splines")
        )
        self._step_points = self.interpolation is Interpolation.NONE  # hold each point, no splines
        self.max_trajectory_points = int(
            params.number("max_trajectory_points", DEFAULT_MAX_POINTS, minimum=1)
        )

        nj = len(self.joints)
        self._pos_cols = self.state_columns("state_interfaces", [f"{j}/position" for j in self.joints])
        self._vel_cols = (
            self.state_columns("state_interfaces", [f"{j}/velocity" for j in self.joints])
            if "velocity" in self.state_kinds
            else None
        )
        if "acceleration" in self.state_kinds:
            self.state_columns("state_interfaces", [f"{j}/acceleration" for j in self.joints])
        self._cmd: list[tuple[str, np.ndarray]] = []
        for kind in self.command_kinds:
            self._cmd.append(
                (kind, self.claim("command_interfaces", [f"{j}/{kind}" for j in command_joints]))
            )

        # PID for a lone velocity or effort interface (ros2_control: required for effort)
        self._pid = self.command_kinds in (("velocity",), ("effort",))
        self.kp, self.ki, self.kd = np.zeros(nj), np.zeros(nj), np.zeros(nj)
        self.i_clamp = np.full(nj, np.inf)
        self.ff_velocity_scale = np.zeros(nj) if self.command_kinds == ("effort",) else np.ones(nj)
        for k, j in enumerate(self.joints):
            params.keys_under(f"gains.{j}")
            if params.has(f"gains.{j}.p") or params.has(f"gains.{j}.d") or params.has(f"gains.{j}.i"):
                self.kp[k] = params.number(f"gains.{j}.p", 0.0)
                self.ki[k] = params.number(f"gains.{j}.i", 0.0)
                self.kd[k] = params.number(f"gains.{j}.d", 0.0)
                self.i_clamp[k] = (
                    params.number(f"gains.{j}.i_clamp", np.inf)
                    if params.has(f"gains.{j}.i_clamp")
                    else np.inf
                )
                if params.has(f"gains.{j}.i_clamp_max"):
                    self.i_clamp[k] = params.number(f"gains.{j}.i_clamp_max")
                self.ff_velocity_scale[k] = params.number(
                    f"gains.{j}.ff_velocity_scale", float(self.ff_velocity_scale[k])
                )
            elif self.command_kinds == ("effort",):
                raise params.error(
                    f"gains.{j}",
                    "missing: an effort command interface needs PID gains (gains.<joint>.p, .i, .d)",
                )

        W = self.nworld
        self.reference_position = np.zeros((W, nj))
        self.reference_velocity = np.zeros((W, nj))
        self.reference_acceleration = np.zeros((W, nj))
        self.feedback_position = np.zeros((W, nj))
        self.feedback_velocity = np.zeros((W, nj))
        self.error_position = np.zeros((W, nj))
        self.error_velocity = np.zeros((W, nj))
        self.output = np.zeros((W, sum(len(c) for _, c in self._cmd)))
        self.executing = np.zeros(W, bool)
        self._i_term = np.zeros((W, nj))
        self._hold = np.zeros((W, nj))  # the reference of a world with no running trajectory
        # the reference came from a trajectory (since the last reset or stop): a partial
        # goal's other joints then hold the reference, not the measured position
        self._on_trajectory = np.zeros(W, bool)

        self._pool = _SegmentPool(W, nj)
        # the running trajectory: block rows 0..last, `segment` the row time has reached
        self._running = np.zeros(W, bool)
        self._t0 = np.zeros(W)  # its start, sim time
        self._segment = np.zeros(W, np.int64)
        self._last = np.zeros(W, np.int64)
        # the trajectory waiting to start: its points are block rows 1..npoint
        self._pending_start = np.full(W, np.inf)
        self._pending_npoint = np.zeros(W, np.int64)
        self._pending_spline = np.zeros(W, np.int8)
        self._pending_mask = np.zeros((W, nj), bool)

    # --- what the buffers hold ---
    @property
    def pending(self) -> np.ndarray:
        """(nworld,) bool: a trajectory is queued and waiting for its start time."""
        return np.isfinite(self._pending_start)

    @property
    def buffer_rows(self) -> int:
        """Trajectory rows allocated for the whole fleet (each ~(6 * njoint + 1) float64)."""
        return self._pool.capacity

    # --- input (from the loop thread) ---
    def set_trajectory(
        self,
        world: int,
        joint_names: Sequence[str],
        times: Sequence[float],
        positions: Sequence[Sequence[float]],
        velocities: Sequence[Sequence[float]] | None = None,
        accelerations: Sequence[Sequence[float]] | None = None,
        start_time: float = 0.0,
    ) -> None:
        """Queue a trajectory for one world: a JointTrajectory's joint_names, points and stamp.

        The one-world convenience over `set_trajectories`.

        Args:
          world: which world.
          joint_names: the message's joint order.
          times: (npoint,) each point's time_from_start, seconds, strictly increasing.
          positions: (npoint, len(joint_names)).
          velocities, accelerations: the same shape, or None / empty when the points carry none.
          start_time: the header stamp in sim time; 0 starts at the next update.

        Raises:
          ValueError: the trajectory is rejected; the world keeps what it was doing.
        """
        w = self._world(world)
        names = list(joint_names)
        unknown = [n for n in names if n not in self.joints]
        if unknown:
            raise ValueError(
                f"{self.name}: unknown joint {unknown[0]!r} (controller joints: {', '.join(self.joints)})"
            )
        if len(set(names)) != len(names):
            raise ValueError(f"{self.name}: joint_names lists a joint twice: {names}")
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        n, nj = t.size, len(self.joints)
        cols = np.array([self.joints.index(j) for j in names], dtype=np.intp)
        mask = np.zeros(nj, bool)
        mask[cols] = True

        def table(values: Any, what: str, required: bool) -> np.ndarray | None:
            if values is None or (np.size(values) == 0 and not required):
                return None
            try:
                a = np.asarray(values, dtype=np.float64)
            except ValueError:
                raise ValueError(f"{self.name}: every point's {what} must have {len(names)} values") from None
            if a.shape != (n, len(names)):
                raise ValueError(
                    f"{self.name}: {what} must be {n} points x {len(names)} joints, got shape {a.shape}"
                )
            full = np.zeros((n, nj))
            full[:, cols] = a
            return full

        if n == 0:  # an empty trajectory stops the world: its points' fields do not matter
            p, v, a = np.zeros((0, nj)), None, None
        else:
            p = table(positions, "positions", True)
            v = table(velocities, "velocities", False)
            a = table(accelerations, "accelerations", False)
        batch = TrajectoryBatch(
            worlds=np.array([w]),
            start_time=np.array([start_time], dtype=np.float64),
            joint_mask=mask[None],
            offsets=np.array([0, n]),
            times=t,
            positions=p,
            velocities=v,
            accelerations=a,
        )
        rejected = self.set_trajectories(batch)
        if rejected:
            raise ValueError(rejected[0][1])

    def set_trajectories(self, batch: TrajectoryBatch) -> list[tuple[int, str]]:
        """Queue every trajectory of a batch, as set_trajectory would one by one, in one vectorized pass.

        Returns (index in the batch, reason) for each rejected trajectory, in batch order;
        the others are queued (a later one for a world replaces an earlier one).

        Raises:
          ValueError: the batch itself is malformed (shapes, offsets): the sender's bug.
        """
        b = self._unpack(batch)
        n, npoint = len(b.worlds), len(b.times)
        if n == 0:
            return []
        counts = b.counts
        owner = np.repeat(np.arange(n), counts)  # (npoint,) the trajectory of each point
        empty = counts == 0
        named = b.joint_mask[owner]  # (npoint, nj)

        def per_trajectory(bad_point: np.ndarray) -> np.ndarray:
            return np.bincount(owner, weights=bad_point, minlength=n) > 0

        # the checks of single points: one pass over the points, the per-check split only if needed
        points = self._points(b, owner, named)
        magnitude = np.stack([np.abs(x).max(axis=1, initial=0.0) for x in points])  # (3, npoint), NaN: NaN
        disorder = np.zeros(npoint, bool)  # a point not after the one before it
        disorder[1:] = ~(b.steps > 0) & (owner[1:] == owner[:-1])
        point_checks = [
            ~(np.isfinite(b.times) & (b.times >= 0)),
            disorder,
            *~(magnitude < MAX_COMMAND),  # positions, velocities, accelerations
        ]
        none = np.zeros(n, bool)
        if per_trajectory(np.logical_or.reduce(point_checks)).any():
            bad_time, bad_order, bad_p, bad_v, bad_a = (per_trajectory(c) for c in point_checks)
        else:
            bad_time = bad_order = bad_p = bad_v = bad_a = none
        last_time = b.times[np.maximum(b.offsets[1:] - 1, 0)] if npoint else np.zeros(n)
        # (failing trajectories, reason for one of them): the first that fails names the reason
        checks = [
            (
                b.bad_world,
                lambda k: (
                    f"world {b.worlds_given[k].item()!r} is out of range: worlds are 0..{self.nworld - 1}"
                ),
            ),
            (~np.isfinite(b.start_time), lambda k: f"start time must be finite, got {b.start_time[k]}"),
            (
                ~empty & ~b.joint_mask.all(axis=1) & (not self.allow_partial),
                lambda k: (
                    f"the trajectory lacks joint {self._missing(b.joint_mask[k])!r} and "
                    "allow_partial_joints_goal is false"
                ),
            ),
            (
                counts > self.max_trajectory_points,
                lambda k: (
                    f"the trajectory has {counts[k]} points, more than max_trajectory_points "
                    f"({self.max_trajectory_points})"
                ),
            ),
            (
                bad_time,
                lambda k: (
                    "time_from_start must be finite and >= 0, got "
                    f"{b.times[b.offsets[k] : b.offsets[k + 1]].tolist()}"
                ),
            ),
            (bad_order, lambda k: self._order_reason(b, k)),
            (bad_p, lambda k: self._value_reason(b, k, "positions")),
            (bad_v, lambda k: self._value_reason(b, k, "velocities")),
            (
                b.has_accelerations & ~b.has_velocities,
                lambda k: "points give accelerations without velocities",
            ),
            (bad_a, lambda k: self._value_reason(b, k, "accelerations")),
            (
                ~empty & (b.start_time > 0) & (b.start_time + last_time < self.time),
                lambda k: (
                    f"the trajectory ends at {b.start_time[k] + last_time[k]:g} s, before the "
                    f"current time {self.time:g} s"
                ),
            ),
        ]
        failed = np.logical_or.reduce([bad for bad, _ in checks])
        rejected: dict[int, str] = {}
        if failed.any():
            for k in np.flatnonzero(failed).tolist():  # the first check it fails names the reason
                reason = next(reason for bad, reason in checks if bad[k])
                rejected[k] = f"{self.name}: {reason(k)}"

        spline = np.where(b.has_accelerations, _QUINTIC, np.where(b.has_velocities, _CUBIC, _LINEAR)).astype(
            np.int8
        )
        reach = self._reach(b, owner, spline, points, magnitude, failed | empty)
        too_far = per_trajectory(~(reach < MAX_COMMAND)) & ~failed
        for k in np.flatnonzero(too_far).tolist():
            point = int(np.argmax(~(reach[b.offsets[k] : b.offsets[k + 1]] < MAX_COMMAND)))
            where = "the start (from rest)" if point == 0 else f"point {point - 1}"
            rejected[k] = (
                f"{self.name}: between {where} and point {point} the trajectory's commands may reach "
                f"{reach[b.offsets[k] + point]:.3g} (a bound), beyond the {MAX_COMMAND:g} write() accepts"
            )
        failed |= too_far

        rows = self._rows(b, owner, spline, points)
        self._queue(b, np.flatnonzero(~failed), counts, spline, rows)
        return sorted(rejected.items())

    def _unpack(self, batch: TrajectoryBatch) -> _Unpacked:
        """The batch's arrays, typed and shape-checked; ValueError naming what is malformed."""
        nj = len(self.joints)

        def malformed(what: str) -> ValueError:
            return ValueError(f"{self.name}: malformed TrajectoryBatch: {what}")

        given = np.asarray(batch.worlds).reshape(-1)
        n = given.size
        if given.dtype.kind in "iu":
            integral = np.ones(n, bool)
        elif given.dtype.kind == "f":
            integral = np.isfinite(given) & (given == np.round(given))
        else:
            raise malformed(f"worlds must be integers, got {given.dtype}")
        worlds = np.where(integral, given, -1).astype(np.int64)
        bad_world = ~integral | (worlds < 0) | (worlds >= self.nworld)
        worlds[bad_world] = 0

        def array(value: Any, shape: tuple[int, ...], dtype: Any, what: str) -> np.ndarray:
            a = np.asarray(value, dtype=dtype)
            if a.shape != shape:
                raise malformed(f"{what} must have shape {shape}, got {a.shape}")
            return a

        offsets = array(batch.offsets, (n + 1,), np.int64, "offsets")
        counts = np.diff(offsets)
        if offsets[0] != 0 or (counts < 0).any():
            raise malformed("offsets must start at 0 and never decrease")
        npoint = int(offsets[-1])
        start = array(batch.start_time, (n,), np.float64, "start_time")
        mask = array(batch.joint_mask, (n, nj), bool, "joint_mask")
        times = array(batch.times, (npoint,), np.float64, "times")
        positions = array(batch.positions, (npoint, nj), np.float64, "positions")
        tables = []
        for values, has, what in (
            (batch.velocities, batch.has_velocities, "velocities"),
            (batch.accelerations, batch.has_accelerations, "accelerations"),
        ):
            if values is None:
                tables += [None, np.zeros(n, bool)]
                continue
            tables.append(array(values, (npoint, nj), np.float64, what))
            tables.append(np.ones(n, bool) if has is None else array(has, (n,), bool, f"has_{what}"))
        steps = np.diff(times)
        return _Unpacked(
            given, worlds, bad_world, start, mask, offsets, counts, times, steps, positions, *tables
        )

    def _missing(self, mask: np.ndarray) -> str:
        return self.joints[int(np.argmin(mask))]

    def _order_reason(self, b: _Unpacked, k: int) -> str:
        t = b.times[b.offsets[k] : b.offsets[k + 1]]
        i = int(np.flatnonzero(~(np.diff(t) > 0))[0]) + 1
        return (
            f"time_from_start must be strictly increasing: point {i} at {t[i]:g} s "
            f"follows point {i - 1} at {t[i - 1]:g} s"
        )

    def _value_reason(self, b: _Unpacked, k: int, what: str) -> str:
        values = getattr(b, what)[b.offsets[k] : b.offsets[k + 1]][:, b.joint_mask[k]]
        if not np.isfinite(values).all():
            return f"{what} must be finite"
        worst = float(values.flat[np.argmax(np.abs(values))])
        return f"{what} must be below {MAX_COMMAND:g} in magnitude (write() refuses larger commands), got {worst:g}"

    def _points(self, b: _Unpacked, owner: np.ndarray, named: np.ndarray) -> tuple[np.ndarray, ...]:
        """(p, v, a), each (npoint, njoint): the points' values, 0 for joints or fields not given."""
        p = np.where(named, b.positions, 0.0)
        v = np.zeros_like(p) if b.velocities is None else np.where(named, b.velocities, 0.0)
        a = np.zeros_like(p) if b.accelerations is None else np.where(named, b.accelerations, 0.0)
        if not b.has_velocities.all():
            v[~b.has_velocities[owner]] = 0.0
        if not b.has_accelerations.all():
            a[~b.has_accelerations[owner]] = 0.0
        return p, v, a

    def _reach(
        self,
        b: _Unpacked,
        owner: np.ndarray,
        spline: np.ndarray,
        points: tuple[np.ndarray, ...],
        magnitude: np.ndarray,
        skip: np.ndarray,
    ) -> np.ndarray:
        """(npoint,) a bound on the commands the segment ending at each point gives (the first
        point's: from rest at time 0); 0 for the points of `skip` and first points at time 0.

        A cheap bound from the segment's end values screens every segment; the polynomial's
        own bound is computed only for the few the cheap one cannot clear.
        """
        p, v, a = points
        npoint = len(p)
        if npoint == 0:
            return np.zeros(0)
        with np.errstate(all="ignore"):
            mp, mv, ma = magnitude  # (npoint,) each: the largest |value| of each point
            first = np.zeros(npoint, bool)
            first[b.offsets[:-1][b.offsets[:-1] < npoint]] = True
            T = np.concatenate([b.times[:1], b.steps])
            T[first] = b.times[first]
            ignore = skip[owner] | (first & ~(T > 0))  # a first point at time 0 is dropped at the start
            if self._step_points:  # each point is commanded as given
                reach = self._command_bound(mp, mv, ma)
                reach[ignore] = 0.0
                return reach
            # the end values bound a Hermite segment's position, velocity and acceleration:
            # |basis| <= 1, its derivatives <= ~6 / T^k; 100 leaves room for the cubic's own a.
            # First the whole batch at once, from its largest values and longest and shortest segments
            used = T[~ignore]
            longest, shortest = used.max(initial=1.0), used[used > 0].min(initial=1.0)
            Mp, Mv, Ma = mp.max(initial=0.0), mv.max(initial=0.0), ma.max(initial=0.0)
            whole = 100.0 * self._command_bound(
                Mp + Mv * longest + Ma * longest**2,
                Mp / shortest + Mv + Ma * longest,
                Mp / shortest**2 + Mv / shortest + Ma,
            )
            if whole < MAX_COMMAND:
                return np.zeros(npoint)
            m = magnitude
            Mp, Mv, Ma = np.maximum(
                m, np.where(first, 0.0, np.concatenate([np.zeros((3, 1)), m[:, :-1]], axis=1))
            )
            safe = np.where(T > 0, T, 1.0)
            reach = 100.0 * self._command_bound(
                Mp + Mv * safe + Ma * safe**2, Mp / safe + Mv + Ma * safe, Mp / safe**2 + Mv / safe + Ma
            )
            reach[ignore] = 0.0
            close = np.flatnonzero(~(reach < MAX_COMMAND))
            if close.size:  # the polynomial's own bound, sum |c_k| s^k over the segment
                start = first[close][:, None]
                before = np.maximum(close - 1, 0)
                c = _coefficients(
                    spline[owner[close]],
                    np.where(start, 0.0, p[before]),
                    p[close],
                    np.where(start, 0.0, v[before]),
                    v[close],
                    np.where(start, 0.0, a[before]),
                    a[close],
                    safe[close, None],
                )
                powers = safe[close, None, None] ** np.arange(6)[:, None]  # (n, 6, 1)
                mag = np.abs(np.stack(c, axis=1))  # (n, 6, nj)
                position = (mag * powers).sum(axis=1)
                velocity = (mag[:, 1:] * np.arange(1, 6)[:, None] * powers[:, :5]).sum(axis=1)
                acceleration = (mag[:, 2:] * np.array([2, 6, 12, 20])[:, None] * powers[:, :4]).sum(axis=1)
                reach[close] = self._command_bound(position, velocity, acceleration).max(axis=1)
        return reach

    def _command_bound(
        self, position: np.ndarray, velocity: np.ndarray, acceleration: np.ndarray
    ) -> np.ndarray:
        """A bound on the commands, from bounds on the reference's position, velocity and acceleration."""
        if self._pid:  # the measured state adds what the PID makes of it: physical, so small
            kv = np.abs(self.ff_velocity_scale) + np.abs(self.kd)
            kp = np.abs(self.kp)
            if np.ndim(position) < 2:  # one bound for every joint
                kv, kp = kv.max(), kp.max()
            return kv * velocity + kp * position
        reference = {"position": position, "velocity": velocity, "acceleration": acceleration}
        return np.maximum.reduce([reference[kind] for kind, _ in self._cmd])

    def _rows(
        self, b: _Unpacked, owner: np.ndarray, spline: np.ndarray, points: tuple[np.ndarray, ...]
    ) -> np.ndarray:
        """(npoint, 6, njoint): each point's pool row, the polynomial of the segment to the next
        point (the last point's, and every point's with interpolation none: its p, v, a / 2)."""
        p, v, a = points
        npoint, nj = p.shape
        rows = np.empty((npoint, 6, nj))
        if self._step_points or npoint < 2:
            held = np.arange(npoint)
        else:
            # every point to the next, across trajectories too (those rows are overwritten below)
            T = b.steps[:, None]
            with np.errstate(all="ignore"):
                c = _coefficients(spline[owner[:-1]], p[:-1], p[1:], v[:-1], v[1:], a[:-1], a[1:], T)
            for k in range(6):
                rows[:-1, k] = c[k]
            held = b.offsets[1:][b.offsets[1:] > b.offsets[:-1]] - 1  # each trajectory's last point
        rows[held, 0], rows[held, 1], rows[held, 2] = p[held], v[held], 0.5 * a[held]
        rows[held, 3:] = 0.0
        return rows

    def _queue(
        self, b: _Unpacked, accepted: np.ndarray, counts: np.ndarray, spline: np.ndarray, rows: np.ndarray
    ) -> None:
        """Store the accepted trajectories (the last per world) as their worlds' pending ones."""
        if not accepted.size:
            return
        keep = accepted[last_per_world(b.worlds[accepted])]
        worlds, npoint = b.worlds[keep], counts[keep]
        pool = self._pool
        pool.release(_PENDING, worlds)  # a newer goal replaces one still waiting to start
        filled = npoint > 0
        pool.allocate(_PENDING, worlds[filled], npoint[filled] + 1)  # + the start row
        off = pool.offset[_PENDING, worlds[filled]]
        dest = ranges(off + 1, npoint[filled])
        if len(dest) == len(rows):  # every point is kept (the usual case): no gather
            pool.times[dest], pool.coefficients[dest] = b.times, rows
        else:
            source = ranges(b.offsets[keep][filled], npoint[filled])
            pool.times[dest] = b.times[source]
            pool.coefficients[dest] = rows[source]
        self._pending_start[worlds] = b.start_time[keep]
        self._pending_npoint[worlds] = npoint
        self._pending_spline[worlds] = spline[keep]
        self._pending_mask[worlds] = b.joint_mask[keep]

    def _start(self, due: np.ndarray, time: float) -> None:
        """Make the due worlds' queued trajectories their running ones, from the current state."""
        pool = self._pool
        nj = len(self.joints)
        t0 = np.where(self._pending_start[due] > 0, self._pending_start[due], time)
        npoint = self._pending_npoint[due]
        here = (self.reference_position if self.open_loop else self.feedback_position)[due]
        if self.open_loop:
            here_v = self.reference_velocity[due]
        elif self._vel_cols is not None:
            here_v = self.feedback_velocity[due]
        else:
            here_v = np.zeros((len(due), nj))
        # the first point still ahead: points already in the past at the start are dropped
        off = pool.offset[_PENDING, due]
        skip = np.zeros(len(due), np.int64)
        late = npoint > 0
        late[late] = t0[late] + pool.times[off[late] + 1] <= time
        if late.any():  # times increase, so the passed points are a prefix: count them
            passed = ranges(off[late] + 1, npoint[late])
            which = np.repeat(np.arange(int(late.sum())), npoint[late])
            gone = np.repeat(t0[late], npoint[late]) + pool.times[passed] <= time
            skip[late] = np.bincount(which, weights=gone, minlength=int(late.sum())).astype(np.int64)
        stop = skip >= npoint
        stopped = due[stop]
        pool.release(_RUNNING, stopped)
        pool.release(_PENDING, stopped)
        pool.trim(stopped)
        self._running[stopped] = False
        self._on_trajectory[stopped] = False
        self._hold[stopped] = here[stop]

        go = ~stop
        worlds = due[go]
        if worlds.size:
            hold = np.where(self._on_trajectory[worlds, None], self.reference_position[worlds], here[go])
            pool.promote(worlds)
            self._begin(worlds, t0[go], time, skip[go], here[go], here_v[go], hold)
        self._pending_start[due] = np.inf
        self._pending_npoint[due] = 0

    def _begin(
        self,
        worlds: np.ndarray,
        t0: np.ndarray,
        time: float,
        skip: np.ndarray,
        here: np.ndarray,
        here_v: np.ndarray,
        hold: np.ndarray,
    ) -> None:
        """Insert the current point before the first point ahead and set the worlds running."""
        pool = self._pool
        off = pool.offset[_RUNNING, worlds]
        npoint = self._pending_npoint[worlds]
        mask = self._pending_mask[worlds]
        spline = self._pending_spline[worlds]
        start_row, first = off + skip, off + skip + 1
        rel = time - t0
        row = np.zeros((len(worlds), 6, len(self.joints)))
        if self._step_points:
            row[:, 0], row[:, 1] = here, here_v
        else:
            # the first point ahead, from its row (a point's row starts with its p, v and a / 2)
            c = pool.coefficients[first]
            p1 = np.where(mask, c[:, 0], hold)
            v1 = np.where(mask & (spline >= _CUBIC)[:, None], c[:, 1], 0.0)
            a1 = np.where(mask & (spline == _QUINTIC)[:, None], 2 * c[:, 2], 0.0)
            T = pool.times[first] - rel
            T = np.where(T > 0, T, 1.0)[:, None]  # a zero-length segment is never sampled
            for k, plane in enumerate(
                _coefficients(spline, here, p1, here_v, v1, np.zeros_like(here), a1, T)
            ):
                row[:, k] = plane
        pool.times[start_row] = rel
        pool.coefficients[start_row] = row
        partial = ~mask.all(axis=1)
        if partial.any():  # joints a partial goal leaves out hold after the first segment
            rows = ranges(first[partial], npoint[partial] - skip[partial])
            which = np.repeat(np.flatnonzero(partial), npoint[partial] - skip[partial])
            block = pool.coefficients[rows]  # (n, 6, nj)
            out = ~mask[which]
            block.transpose(0, 2, 1)[out] = 0.0
            block[:, 0][out] = hold[which][out]
            pool.coefficients[rows] = block
        self._t0[worlds] = t0
        self._segment[worlds] = skip
        self._last[worlds] = npoint
        self._running[worlds] = True
        self._on_trajectory[worlds] = True
        self._i_term[worlds] = 0.0

    def topics(self) -> ControllerTopics:
        """`<ns>/<controller>/joint_trajectory` in; `<ns>/<controller>/controller_state/
        {reference, feedback, error}` out, as JointState (control_msgs is not on PyPI):
        reference carries the reference acceleration in its effort field."""
        names = tuple(self.joints)
        state = f"{self.name}/controller_state"

        def reference() -> dict[str, np.ndarray]:
            return {
                "position": self.reference_position,
                "velocity": self.reference_velocity,
                "effort": self.reference_acceleration,
            }

        def feedback() -> dict[str, np.ndarray]:
            return {"position": self.feedback_position, "velocity": self.feedback_velocity}

        def error() -> dict[str, np.ndarray]:
            return {"position": self.error_position, "velocity": self.error_velocity}

        return ControllerTopics(
            self.name,
            inputs=(
                Input(
                    f"{self.name}/joint_trajectory",
                    MessageKind.JOINT_TRAJECTORY,
                    self.set_trajectories,
                    joints=names,
                ),
            ),
            outputs=tuple(
                Output(f"{state}/{part}", MessageKind.JOINT_STATE, read, names=names)
                for part, read in (("reference", reference), ("feedback", feedback), ("error", error))
            ),
        )

    # --- the loop ---
    def activate(self, sim: Any, time: float) -> None:
        self._read(sim)
        self._hold[:] = self.feedback_position
        self.reference_position[:] = self.feedback_position

    def reset(self, sim: Any, worlds: np.ndarray) -> None:
        self._read(sim)
        self._pool.release(_RUNNING, worlds)
        self._pool.release(_PENDING, worlds)
        self._pool.trim(worlds)
        self._pool.shrink()
        self._running[worlds] = False
        self._on_trajectory[worlds] = False
        self._hold[worlds] = self.feedback_position[worlds]
        self.reference_position[worlds] = self.feedback_position[worlds]
        self.reference_velocity[worlds] = 0.0
        self.reference_acceleration[worlds] = 0.0
        self.executing[worlds] = False
        self._i_term[worlds] = 0.0
        self._pending_start[worlds] = np.inf
        self._pending_npoint[worlds] = 0

    def _read(self, sim: Any) -> None:
        state = sim.state
        self.feedback_position[:] = state[:, self._pos_cols]
        if self._vel_cols is not None:
            self.feedback_velocity[:] = state[:, self._vel_cols]

    def update(self, sim: Any, time: float, period: float) -> None:
        self._read(sim)
        if self._pending_start.min() <= time + 1e-9:
            self._start(np.flatnonzero(self._pending_start <= time + 1e-9), time)
        self._sample(time)
        self._pool.shrink()
        self.error_position[:] = self.reference_position - self.feedback_position
        self.error_velocity[:] = self.reference_velocity - self.feedback_velocity
        self._command(sim, period)

    def _sample(self, time: float) -> None:
        """Reference position/velocity/acceleration of every world at `time`."""
        pos, vel, acc = self.reference_position, self.reference_velocity, self.reference_acceleration
        running = np.flatnonzero(self._running)
        if len(running) < self.nworld:
            pos[:] = self._hold
            vel[:] = 0.0
            acc[:] = 0.0
            self.executing[:] = False
        if not running.size:
            return
        pool = self._pool
        times = pool.times
        rel = time - self._t0[running]
        base = pool.offset[_RUNNING, running]
        segment, last = self._segment[running], self._last[running]
        # segment: the last point at or before rel; usually the same as last period or the next
        moving = np.flatnonzero(
            (segment < last) & (times[base + np.minimum(segment + 1, last)] <= rel + 1e-12)
        )
        while moving.size:
            segment[moving] += 1
            s = segment[moving]
            ahead = (s < last[moving]) & (
                times[base[moving] + np.minimum(s + 1, last[moving])] <= rel[moving] + 1e-12
            )
            moving = moving[ahead]
        self._segment[running] = segment
        row = base + segment
        done = segment >= last
        # position, velocity and acceleration as one product: (n, 3, 6) derivatives of s^k @ (n, 6, nj)
        basis = np.zeros((len(running), 3, 6))
        if self._step_points:
            basis[:, 0, 0], basis[:, 1, 1], basis[:, 2, 2] = 1.0, 1.0, 2.0
        else:
            powers = np.ones((len(running), 6))
            powers[:, 1:] = np.maximum(rel - times[row], 0.0)[:, None]
            np.cumprod(powers, axis=1, out=powers)
            basis[:, 0] = powers
            basis[:, 1, 1:] = powers[:, :5] * _D1
            basis[:, 2, 2:] = powers[:, :4] * _D2
        basis[done] = _HOLD  # past the last point: its position, at rest
        reference = basis @ pool.coefficients[row]
        pos[running], vel[running], acc[running] = reference[:, 0], reference[:, 1], reference[:, 2]
        self.executing[running] = ~done
        finished = running[done]
        if finished.size:  # past the last point: hold it and give the rows back
            self._hold[finished] = pos[finished]
            self._running[finished] = False
            pool.release(_RUNNING, finished)
            pool.trim(finished)

    def _command(self, sim: Any, period: float) -> None:
        if self._pid:
            e, de = self.error_position, self.error_velocity
            self._i_term += self.ki * e * period
            np.clip(self._i_term, -self.i_clamp, self.i_clamp, out=self._i_term)
            u = self.ff_velocity_scale * self.reference_velocity + self.kp * e + self._i_term + self.kd * de
            kind, cols = self._cmd[0]
            self.output[:] = u
            sim.command[:, cols] = u
            return
        start = 0
        for kind, cols in self._cmd:
            value = {
                "position": self.reference_position,
                "velocity": self.reference_velocity,
                "acceleration": self.reference_acceleration,
            }[kind]
            self.output[:, start : start + len(cols)] = value
            sim.command[:, cols] = value
            start += len(cols)


@dataclasses.dataclass
class _Unpacked:
    """A TrajectoryBatch's arrays, typed and checked (see TrajectoryBatch); worlds out of range are 0."""

    worlds_given: np.ndarray
    worlds: np.ndarray
    bad_world: np.ndarray
    start_time: np.ndarray
    joint_mask: np.ndarray
    offsets: np.ndarray
    counts: np.ndarray  # (n,) points per trajectory
    times: np.ndarray
    steps: np.ndarray  # (npoint - 1,) times[1:] - times[:-1]
    positions: np.ndarray
    velocities: np.ndarray | None
    has_velocities: np.ndarray
    accelerations: np.ndarray | None
    has_accelerations: np.ndarray


def _order(kind: str) -> int:
    return (
        ("position", "velocity", "acceleration", "effort").index(kind)
        if kind in ("position", "velocity", "acceleration", "effort")
        else 99
    )


def _coefficients(
    spline: np.ndarray,
    p0: np.ndarray,
    p1: np.ndarray,
    v0: np.ndarray,
    v1: np.ndarray,
    a0: np.ndarray,
    a1: np.ndarray,
    T: np.ndarray,
) -> tuple[np.ndarray, ...]:
    """Segment polynomials: the six (n, njoint) coefficients of s^0 .. s^5.

    Args:
      spline: (n,) Spline of each segment: linear from positions only, cubic Hermite from
        positions and velocities, quintic from all three.
      p0, p1, v0, v1, a0, a1: (n, njoint) the values at the segment's two ends.
      T: (n, 1) its length, > 0.
    """
    kinds = spline[:1] if len(spline) and (spline == spline[0]).all() else np.unique(spline)
    if len(kinds) > 1:
        out = [np.zeros(p0.shape) for _ in range(6)]
        for kind in kinds:
            m = spline == kind
            part = _coefficients(spline[m], p0[m], p1[m], v0[m], v1[m], a0[m], a1[m], T[m])
            for o, c in zip(out, part, strict=True):
                o[m] = c
        return tuple(out)
    h = p1 - p0
    zero = np.broadcast_to(0.0, h.shape)  # a read-only view: no array to fill
    if len(kinds) == 0 or kinds[0] == _LINEAR:
        return p0, h / T, zero, zero, zero, zero
    if kinds[0] == _CUBIC:
        inverse = 1.0 / T
        c2 = (3 * h * inverse - (2 * v0 + v1)) * inverse
        c3 = ((v0 + v1) - 2 * h * inverse) * inverse * inverse
        return p0, v0, c2, c3, zero, zero
    T2 = T * T
    T3 = T2 * T
    b3 = (20 * h - (8 * v1 + 12 * v0) * T - (3 * a0 - a1) * T2) / (2 * T3)
    b4 = (-30 * h + (14 * v1 + 16 * v0) * T + (3 * a0 - 2 * a1) * T2) / (2 * T3 * T)
    b5 = (12 * h - 6 * (v1 + v0) * T + (a1 - a0) * T2) / (2 * T3 * T2)
    return p0, v0, a0 / 2, b3, b4, b5
