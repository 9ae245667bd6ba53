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
  with no points stops the world where it is.
- Rejected (ValueError, the world unchanged): unknown joints, missing joints unless
  `allow_partial_joints_goal`, non-increasing or negative times, mismatched or
  non-finite values, a trajectory that ends before it would start.

Commands: a `position` interface gets the reference position (and `velocity`, when
claimed alongside it, the reference velocity); a lone `velocity` or `effort` interface
gets `ff_velocity_scale * v_ref + PID(error)` with `gains.<joint>.p/i/d/i_clamp/
ff_velocity_scale`, as the stock controller computes it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np

from batchsim.controllers.base import Controller, Params
from batchsim.controllers.topics import ControllerTopics, Input, MessageKind, Output, TrajectoryBatch
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

LINEAR, CUBIC, QUINTIC = 1, 2, 3


@dataclasses.dataclass
class _Goal:
    """A validated trajectory waiting for its start time: every array in controller joint order."""

    start: float  # sim time; 0: the next update
    times: np.ndarray  # (npoint,)
    mask: np.ndarray  # (njoint,) bool: joints the message names
    positions: np.ndarray  # (npoint, njoint), NaN for joints it does not name
    velocities: np.ndarray | None
    accelerations: np.ndarray | None


class JointTrajectoryController(Controller):
    """joint_trajectory_controller/JointTrajectoryController.

    Parameters (stock): `joints`, `command_joints`, `command_interfaces`,
    `state_interfaces`, `allow_partial_joints_goal`, `open_loop_control`,
    `interpolation_method` (splines, none), `gains.<joint>.{p, i, d, i_clamp,
    ff_velocity_scale}`; `constraints.*`, `action_monitor_rate`, `state_publish_rate` and
    the rest are accepted and not acted on.

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
        self.interpolation = params.choice("interpolation_method", ("splines", "none"), "splines")

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
        self._hold = np.zeros((W, nj))

        # the running trajectories, padded to `capacity` points; point 0 is the inserted start
        self._capacity = 0
        self._t0 = np.zeros(W)  # start time (sim time) of each world's trajectory
        self._npt = np.zeros(W, np.intp)  # 0: no trajectory, hold `_hold`
        self._mode = np.full(W, LINEAR, np.int8)
        self._grow(4)
        self._pending: dict[int, _Goal] = {}
        self._pending_start = np.full(W, np.inf)

    def _grow(self, npoint: int) -> None:
        cap = max(npoint, 2 * self._capacity)
        W, nj = self.nworld, len(self.joints)
        times = np.full((W, cap), np.inf)
        arrays = [np.zeros((W, cap, nj)) for _ in range(3)]
        coefficients = np.zeros((W, cap, nj, 6))
        if self._capacity:
            times[:, : self._capacity] = self._times
            for new, old in zip(arrays, (self._P, self._V, self._A), strict=True):
                new[:, : self._capacity] = old
            coefficients[:, : self._capacity] = self._C
        self._times = times
        self._P, self._V, self._A = arrays
        self._C = coefficients  # (W, cap, nj, 6): segment k's polynomial in the time since point k
        self._capacity = cap

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
        missing = [j for j in self.joints if j not in names]
        if missing and not self.allow_partial and np.size(times) > 0:
            raise ValueError(
                f"{self.name}: the trajectory lacks joint {missing[0]!r} and allow_partial_joints_goal is false"
            )
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        n = t.size
        if not np.isfinite(start_time):
            raise ValueError(f"{self.name}: start time must be finite, got {start_time}")
        if n == 0:  # ros2_control: an empty trajectory stops the robot where it is
            self._queue(
                w,
                _Goal(
                    float(start_time),
                    t,
                    np.zeros(len(self.joints), bool),
                    np.zeros((0, len(self.joints))),
                    None,
                    None,
                ),
            )
            return
        if not np.isfinite(t).all() or (t < 0).any():
            raise ValueError(f"{self.name}: time_from_start must be finite and >= 0, got {t.tolist()}")
        if n > 1 and not (np.diff(t) > 0).all():
            k = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1
            raise ValueError(
                f"{self.name}: time_from_start must be strictly increasing: point {k} at {t[k]:g} s "
                f"follows point {k - 1} at {t[k - 1]:g} s"
            )
        cols = np.array([self.joints.index(j) for j in names], dtype=np.intp)
        mask = np.zeros(len(self.joints), bool)
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
            if not np.isfinite(a).all():
                raise ValueError(f"{self.name}: {what} must be finite")
            full = np.full((n, len(self.joints)), np.nan)
            full[:, cols] = a
            return full

        p = table(positions, "positions", True)
        v = table(velocities, "velocities", False)
        a = table(accelerations, "accelerations", False)
        if a is not None and v is None:
            raise ValueError(f"{self.name}: points give accelerations without velocities")
        start = float(start_time)
        if start > 0 and start + t[-1] < self.time:
            raise ValueError(
                f"{self.name}: the trajectory ends at {start + t[-1]:g} s, before the current time {self.time:g} s"
            )
        self._queue(w, _Goal(start, t, mask, p, v, a))

    def set_trajectories(self, batch: TrajectoryBatch) -> list[tuple[int, str]]:
        """Queue every trajectory of a batch, as set_trajectory would one by one.

        Returns (index in the batch, reason) for each rejected trajectory; the others are queued.
        """
        rejected: list[tuple[int, str]] = []
        for k in range(len(batch)):
            lo, hi = int(batch.offsets[k]), int(batch.offsets[k + 1])
            mask = np.asarray(batch.joint_mask[k], bool)
            names = [j for j, named in zip(self.joints, mask, strict=True) if named]

            given = [
                None if values is None or has is None or not has[k] else values[lo:hi][:, mask]
                for values, has in (
                    (batch.velocities, batch.has_velocities),
                    (batch.accelerations, batch.has_accelerations),
                )
            ]
            try:
                self.set_trajectory(
                    int(batch.worlds[k]),
                    names,
                    batch.times[lo:hi],
                    batch.positions[lo:hi][:, mask],
                    *given,
                    start_time=float(batch.start_time[k]),
                )
            except ValueError as e:
                rejected.append((k, str(e)))
        return rejected

    def _queue(self, w: int, goal: _Goal) -> None:
        self._pending[w] = goal  # a newer goal for a world replaces one still waiting to start
        self._pending_start[w] = goal.start

    def _start(self, sim: Any, w: int, goal: _Goal, time: float) -> None:
        """Make a queued goal world w's running trajectory, from the current state."""
        nj = len(self.joints)
        here = self.reference_position[w] if self.open_loop else self.feedback_position[w]
        here_v = (
            self.reference_velocity[w]
            if self.open_loop
            else self.feedback_velocity[w]
            if self._vel_cols is not None
            else np.zeros(nj)
        )
        self._pending.pop(w, None)
        self._pending_start[w] = np.inf
        t0 = goal.start if goal.start > 0 else time
        keep = t0 + goal.times > time  # points already in the past are dropped
        if goal.times.size == 0 or not keep.any():
            self._npt[w] = 0
            self._hold[w] = here
            self.executing[w] = False
            return
        times = goal.times[keep]
        npt = times.size + 1
        if npt > self._capacity:
            self._grow(npt)
        # joints a partial goal leaves out hold their current reference
        hold = self.reference_position[w] if self._npt[w] or self.open_loop else here
        P = np.where(goal.mask, goal.positions[keep], hold)
        V = np.zeros_like(P) if goal.velocities is None else np.where(goal.mask, goal.velocities[keep], 0.0)
        A = (
            np.zeros_like(P)
            if goal.accelerations is None
            else np.where(goal.mask, goal.accelerations[keep], 0.0)
        )
        self._t0[w] = t0
        self._times[w] = np.inf
        self._times[w, 0] = time - t0
        self._times[w, 1:npt] = times
        self._P[w, 0], self._V[w, 0], self._A[w, 0] = here, here_v, 0.0
        self._P[w, 1:npt], self._V[w, 1:npt], self._A[w, 1:npt] = P, V, A
        self._npt[w] = npt
        mode = QUINTIC if goal.accelerations is not None else CUBIC if goal.velocities is not None else LINEAR
        self._mode[w] = mode
        # each segment's polynomial, once per trajectory rather than every period
        P, V, A = self._P[w, :npt], self._V[w, :npt], self._A[w, :npt]
        T = np.diff(self._times[w, :npt])
        T = np.where(T > 0, T, 1.0)[:, None]  # a zero-length segment is never sampled
        self._C[w, : npt - 1] = _coefficients(mode, P[:-1], P[1:], V[:-1], V[1:], A[:-1], A[1:], T)
        self._i_term[w] = 0.0

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
        self._npt[worlds] = 0
        self._hold[worlds] = self.feedback_position[worlds]
        self.reference_position[worlds] = self.feedback_position[worlds]
        self.reference_velocity[worlds] = 0.0
        self.reference_acceleration[worlds] = 0.0
        self.executing[worlds] = False
        self._i_term[worlds] = 0.0
        for w in worlds.tolist():
            self._pending.pop(int(w), None)
        self._pending_start[worlds] = np.inf

    def _read(self, sim: Any) -> None:
        state = sim.state
        self.feedback_position[:] = state[:, self._pos_cols]
        if self._vel_cols is not None:
            self.feedback_velocity[:] = state[:, self._vel_cols]

    def update(self, sim: Any, time: float, period: float) -> None:
        self._read(sim)
        if self._pending:
            for w in np.flatnonzero(self._pending_start <= time + 1e-9).tolist():
                self._start(sim, w, self._pending[w], time)
        self._sample(time)
        self.error_position[:] = self.reference_position - self.feedback_position
        self.error_velocity[:] = self.reference_velocity - self.feedback_velocity
        self._command(sim, period)

    def _sample(self, time: float) -> None:
        """Reference position/velocity/acceleration of every world at `time`."""
        running = self._npt > 0
        pos, vel, acc = self.reference_position, self.reference_velocity, self.reference_acceleration
        if not running.any():
            pos[:] = self._hold
            vel[:] = 0.0
            acc[:] = 0.0
            self.executing[:] = False
            return
        with np.errstate(invalid="ignore", divide="ignore"):  # idle worlds' padding is inf; masked below
            self._sample_running(time, running)

    def _sample_running(self, time: float, running: np.ndarray) -> None:
        W = self.nworld
        pos, vel, acc = self.reference_position, self.reference_velocity, self.reference_acceleration
        rel = time - self._t0  # (W,)
        # segment k: the last point at or before rel (point 0, the inserted start, is always at or before)
        k = np.maximum((self._times <= rel[:, None] + 1e-12).sum(axis=1) - 1, 0)
        last = np.maximum(self._npt - 1, 0)
        done = k >= last
        k = np.minimum(k, np.maximum(last - 1, 0))
        rows = np.arange(W)
        t_a, t_b = self._times[rows, k], self._times[rows, k + 1]
        if self.interpolation == "none":
            # hold the start point, then each point from its time on
            at_b = (rel >= t_b)[:, None]
            p = np.where(at_b, self._P[rows, k + 1], self._P[rows, k])
            v = np.where(at_b, self._V[rows, k + 1], self._V[rows, k])
            a = np.where(at_b, self._A[rows, k + 1], self._A[rows, k])
        else:
            s = np.clip(rel - t_a, 0.0, None)[:, None]
            c0, c1, c2, c3, c4, c5 = np.moveaxis(self._C[rows, k], -1, 0)  # (W, nj) each
            p = c0 + s * (c1 + s * (c2 + s * (c3 + s * (c4 + s * c5))))
            v = c1 + s * (2 * c2 + s * (3 * c3 + s * (4 * c4 + s * 5 * c5)))
            a = 2 * c2 + s * (6 * c3 + s * (12 * c4 + s * 20 * c5))
        end = self._P[rows, last]
        d = done[:, None]
        r = running[:, None]
        pos[:] = np.where(r, np.where(d, end, p), self._hold)
        vel[:] = np.where(r & ~d, v, 0.0)
        acc[:] = np.where(r & ~d, a, 0.0)
        self.executing[:] = running & ~done

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


def _order(kind: str) -> int:
    return (
        ("position", "velocity", "acceleration", "effort").index(kind)
        if kind in ("position", "velocity", "acceleration", "effort")
        else 99
    )


def _coefficients(mode, p0, p1, v0, v1, a0, a1, T):
    """Segment polynomials, (..., 6) coefficients of s^0..s^5: linear, cubic or quintic by `mode`.

    All three are one quintic: a linear segment is the quintic whose end velocities are the
    chord slope and end accelerations zero; a cubic one has the cubic Hermite spline's own
    end accelerations.
    """
    h = p1 - p0
    if mode == LINEAR:
        v0 = v1 = h / T
        a0 = a1 = np.zeros_like(h)
    elif mode == CUBIC:
        c2 = (3 * h - (2 * v0 + v1) * T) / T**2
        c3 = (-2 * h + (v0 + v1) * T) / T**3
        a0, a1 = 2 * c2, 2 * c2 + 6 * c3 * T
    T2 = T * T
    T3 = T2 * T
    b3 = (20 * h - (8 * v1 + 12 * v0) * T - (3 * a0 - a1) * T2) / (2 * T3)
    b4 = (-30 * h + (14 * v1 + 16 * v0) * T + (3 * a0 - 2 * a1) * T2) / (2 * T3 * T)
    b5 = (12 * h - 6 * (v1 + v0) * T + (a1 - a0) * T2) / (2 * T3 * T2)
    return np.stack([p0, v0, a0 / 2, b3, b4, b5], axis=-1)
