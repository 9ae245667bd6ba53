"""JointTrajectoryController itself: parameters, input, the loop, commands, topics.

Its semantics are the package's docstring (batchsim/controllers/trajectory/__init__.py);
each world's trajectory timeline (and the segment pool under it), the spline math, the
batch checks and the goals live beside it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import numpy as np

from batchsim.controllers.base import Controller, Params
from batchsim.controllers.topics import (
    ActionKind,
    ControllerTopics,
    GoalOutcome,
    Input,
    MessageKind,
    Output,
    TrajectoryBatch,
)
from batchsim.controllers.trajectory import runtime
from batchsim.controllers.trajectory.gains import read_gains
from batchsim.controllers.trajectory.goals import Constraints, GoalTracker
from batchsim.controllers.trajectory.splines import Interpolation
from batchsim.controllers.trajectory.timeline import Timeline
from batchsim.controllers.trajectory.validation import CommandBound, check, one_trajectory, unpack
from batchsim.model import RobotSpec
from batchsim.pid import PidBank
from batchsim.types import ConfigurationError, as_slice

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


class JointTrajectoryController(Controller):
    """joint_trajectory_controller/JointTrajectoryController (semantics: the package's docstring).

    Parameters (stock): `joints`, `command_joints`, `command_interfaces`,
    `state_interfaces`, `allow_partial_joints_goal`, `open_loop_control`,
    `interpolation_method` (splines, none), `gains.<joint>` (control_toolbox's PID parameters,
    `ff_velocity_scale` and `i_clamp`: gains.py), `constraints.{stopped_velocity_tolerance, goal_time,
    <joint>.trajectory, <joint>.goal}` (goals.py; `decelerate_on_cancel` and
    `<joint>.max_deceleration_on_cancel` are read and not acted on); `action_monitor_rate`,
    `state_publish_rate` and the rest are accepted and not acted on. batchsim's own:
    `max_trajectory_points` (default 10,000), the most points a trajectory may have.

    Attributes (all (nworld, njoint), refreshed every update):
      reference_position, reference_velocity, reference_acceleration: the sampled trajectory.
      feedback_position, feedback_velocity: the measured state.
      error_position, error_velocity: reference minus feedback.
      output: the values written to the command interfaces, (nworld, ncommand).
      executing: (nworld,) bool, a trajectory is running and not yet past its last point.
      goal: (nworld,) int64, the tag of the action goal the world follows or last followed
        (TrajectoryBatch.goals); 0: none, or a topic trajectory replaced it.
      outcome: (nworld,) int8 GoalOutcome of that goal (NONE without one).
      outcome_joint: (nworld,) int64, the joint (index into `joints`) that violated a
        tolerance when `outcome` says so; -1 otherwise.
    """

    TYPE: ClassVar[str] = "joint_trajectory_controller/JointTrajectoryController"
    ACCEPTED = (
        *Controller.ACCEPTED,
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
        # per world: set_parameters changes a world's (runtime.py)
        self.allow_partial = np.full(nworld, params.boolean("allow_partial_joints_goal", False))
        self.open_loop = params.boolean("open_loop_control", False)
        self.interpolation = Interpolation(
            params.choice("interpolation_method", [i.value for i in Interpolation], "splines")
        )
        self._step_points = self.interpolation is Interpolation.NONE  # hold each point, no splines
        self.max_trajectory_points = int(
            params.number("max_trajectory_points", DEFAULT_MAX_POINTS, minimum=1)
        )

        nj = len(self.joints)
        # state columns, as slices where they step evenly (batchsim.types.as_slice)
        self._pos_cols = as_slice(self.state_columns("state_interfaces", [f"{j}/position" for j in self.joints]))
        self._vel_cols = (
            as_slice(self.state_columns("state_interfaces", [f"{j}/velocity" for j in self.joints]))
            if "velocity" in self.state_kinds
            else None
        )
        self._acc_cols = (
            as_slice(self.state_columns("state_interfaces", [f"{j}/acceleration" for j in self.joints]))
            if "acceleration" in self.state_kinds
            else None
        )
        self._cmd: list[tuple[str, np.ndarray]] = []
        for kind in self.command_kinds:
            self._cmd.append(
                (kind, self.claim("command_interfaces", [f"{j}/{kind}" for j in command_joints]))
            )

        # PID for a lone velocity or effort interface (ros2_control: required for effort)
        pid = self.command_kinds in (("velocity",), ("effort",))
        gains, self.ff_velocity_scale = read_gains(
            params, self.joints, effort=self.command_kinds == ("effort",)
        )
        self._pids = PidBank(gains, self.nworld) if pid else None
        self._overrides: dict[int, dict[str, Any]] = {}  # world -> the parameters set there at run time
        p, d = (np.array([getattr(g, name) for g in gains]) for name in ("p", "d"))
        self._bound = CommandBound(
            self.command_kinds, pid, np.abs(self.ff_velocity_scale) + np.abs(d), np.abs(p)
        )
        self.constraints = Constraints.read(params, self.joints)
        self._runtime = runtime.declared(self.joints, self.constraints, gains, self.ff_velocity_scale, bool(self.allow_partial[0]))
        self._goals = GoalTracker(self.nworld, self.constraints)
        self.goal, self.outcome, self.outcome_joint = (
            self._goals.goal,
            self._goals.outcome,
            self._goals.outcome_joint,
        )
        # the errors upstream computes, and so checks tolerances on (tolerances.hpp)
        self._velocity_error = self._vel_cols is not None and self.command_kinds in (
            ("velocity",),
            ("effort",),
        )
        self._acceleration_error = self._acc_cols is not None and "acceleration" in self.command_kinds

        W = self.nworld
        # the reference and `executing` are the timeline's arrays, written in place
        self._timeline = Timeline(W, nj, step_points=self._step_points)
        self.reference_position, self.reference_velocity, self.reference_acceleration = (
            self._timeline.reference_position,
            self._timeline.reference_velocity,
            self._timeline.reference_acceleration,
        )
        self.executing = self._timeline.executing
        self.feedback_position = np.zeros((W, nj))
        self.feedback_velocity = np.zeros((W, nj))
        self.error_position = np.zeros((W, nj))
        self.error_velocity = np.zeros((W, nj))
        self.output = np.zeros((W, sum(len(c) for _, c in self._cmd)))
        # per claimed kind: the reference written, its columns of output and of the command
        sources = {
            "position": self.reference_position,
            "velocity": self.reference_velocity,
            "acceleration": self.reference_acceleration,
        }
        self._writes: list[tuple[np.ndarray, slice, slice | np.ndarray]] = []
        start = 0
        for kind, cols in self._cmd:
            if kind in sources:
                self._writes.append((sources[kind], slice(start, start + len(cols)), as_slice(cols)))
            start += len(cols)

    # --- what the buffers hold ---
    @property
    def pending(self) -> np.ndarray:
        """(nworld,) bool: a trajectory is queued and waiting for its start time."""
        return self._timeline.pending

    @property
    def buffer_rows(self) -> int:
        """Trajectory rows allocated for the whole fleet (each 3 * njoint + 1 float64)."""
        return self._timeline.pool.capacity

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
        batch = one_trajectory(
            self._world(world),
            joint_names,
            times,
            positions,
            velocities,
            accelerations,
            start_time,
            name=self.name,
            joints=self.joints,
        )
        rejected = self.set_trajectories(batch)
        if rejected:
            raise ValueError(rejected[0][1])

    def set_trajectories(self, batch: TrajectoryBatch) -> list[tuple[int, str]]:
        """Queue every trajectory of a batch, as set_trajectory would one by one, in one vectorized pass.

        Returns (index in the batch, reason) for each rejected trajectory, in batch order;
        the others are queued (a later one for a world replaces an earlier one). An accepted
        trajectory replaces its world's goal: with a tag (`batch.goals`), it is the world's
        new ACTIVE goal; without, the world has none.

        Raises:
          ValueError: the batch itself is malformed (shapes, offsets): the sender's bug.
        """
        b = unpack(batch, name=self.name, nworld=self.nworld, njoint=len(self.joints))
        if len(b.worlds) == 0:
            return []
        verdict = check(
            b,
            name=self.name,
            nworld=self.nworld,
            joints=self.joints,
            allow_partial=self.allow_partial[b.worlds],
            max_points=self.max_trajectory_points,
            time=self.time,
            bound=self._bound,
            step_points=self._step_points,
        )
        keep = self._timeline.queue(b, np.flatnonzero(~verdict.failed), verdict.spline, verdict.points)
        if keep.size:
            self._goals.queue(
                b.worlds[keep],
                b.goals[keep],
                *(
                    None if t is None else t[keep]
                    for t in (b.path_tolerance, b.goal_tolerance, b.goal_time_tolerance)
                ),
            )
        return verdict.rejected

    def cancel(self, worlds: np.ndarray, goals: np.ndarray) -> None:
        """Cancel goals, as upstream's cancel callback: each of `worlds` (n,) whose current goal
        is `goals` (n,) int64 and still ACTIVE becomes CANCELED and holds where it was measured
        at the last update (its queued trajectory is dropped too). Others are left alone.

        Raises:
          ValueError: a world out of range, or shapes that differ (the caller's bug).
        """
        rows, bad = self._batch_worlds(worlds)
        if bad:
            raise ValueError(next(iter(bad.values())))
        tags = np.asarray(goals).reshape(-1)
        if tags.shape != rows.shape:
            raise ValueError(f"{self.name}: cancel: {len(rows)} worlds but {len(tags)} goals")
        self._stop(self._goals.cancel(rows, tags.astype(np.int64)))

    def topics(self) -> ControllerTopics:
        """`<ns>/<controller>/joint_trajectory` in; `<ns>/<controller>/controller_state` out
        (control_msgs/JointTrajectoryControllerState, as upstream), and, deprecated, kept for
        one release, its parts as JointState on `<ns>/<controller>/controller_state/
        {reference, feedback, error}` (reference carries the acceleration in its effort)."""
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

        def controller_state() -> dict[str, np.ndarray]:
            return {
                "reference_positions": self.reference_position,
                "reference_velocities": self.reference_velocity,
                "reference_accelerations": self.reference_acceleration,
                "feedback_positions": self.feedback_position,
                "feedback_velocities": self.feedback_velocity,
                "error_positions": self.error_position,
                "error_velocities": self.error_velocity,
                "output_positions": self.reference_position,
            }

        state_message = Output(state, MessageKind.JOINT_TRAJECTORY_CONTROLLER_STATE, controller_state, names=names)
        return ControllerTopics(
            self.name,
            inputs=(
                Input(
                    f"{self.name}/joint_trajectory",
                    MessageKind.JOINT_TRAJECTORY,
                    self.set_trajectories,
                    joints=names,
                    max_points=self.max_trajectory_points,
                ),
            ),
            outputs=(state_message,)
            + tuple(
                Output(f"{state}/{part}", MessageKind.JOINT_STATE, read, names=names)
                for part, read in (("reference", reference), ("feedback", feedback), ("error", error))
            ),
            action=ActionKind.FOLLOW_JOINT_TRAJECTORY,
        )

    # --- parameters at run time (runtime.py) ---
    def runtime_parameters(self) -> dict[str, Any]:
        return dict(self._runtime)

    def set_parameters(self, worlds: np.ndarray, values: Mapping[str, Any]) -> str:
        why = runtime.refusal(self.name, list(values), self.joints)
        if why:
            return why
        staged = []  # every world's new values, checked before any world changes
        for w in np.unique(np.asarray(worlds, np.int64)).tolist():
            p = Params({**self.params.values, **self._overrides.get(w, {}), **values}, where="set_parameters", controller=self.name)
            try:
                gains, ff = read_gains(p, self.joints, effort=self.command_kinds == ("effort",))
                staged.append((w, gains, ff, Constraints.read(p, self.joints), p.boolean("allow_partial_joints_goal", False)))
            except ConfigurationError as e:
                return str(e)
        for w, gains, ff, constraints, allow in staged:
            self._overrides[w] = {**self._overrides.get(w, {}), **values}
            self.allow_partial[w] = allow
            self._goals.set_defaults(np.array([w]), constraints)
            if self.ff_velocity_scale.ndim == 1:
                self.ff_velocity_scale = np.repeat(self.ff_velocity_scale[None], self.nworld, axis=0)
            self.ff_velocity_scale[w] = ff
            if self._pids is not None:
                self._pids.set_gains(np.array([w]), gains)
                kp, kv = (np.array([abs(getattr(g, k)) for g in gains]) for k in ("p", "d"))
                b = self._bound  # the commands' bound only grows: it covers every world's gains
                self._bound = CommandBound(b.kinds, b.pid, np.maximum(b.kv, np.abs(ff) + kv), np.maximum(b.kp, kp))
        return ""

    # --- the loop ---
    def activate(self, sim: Any, time: float) -> None:
        self._read(sim)
        self._timeline.hold[:] = self.feedback_position
        self.reference_position[:] = self.feedback_position

    def reset(self, sim: Any, worlds: np.ndarray) -> None:
        self._end(sim, worlds, GoalOutcome.ABORTED)

    def deactivate(self, sim: Any, worlds: np.ndarray) -> None:
        self._end(sim, worlds, GoalOutcome.DEACTIVATED)

    def _end(self, sim: Any, worlds: np.ndarray, outcome: GoalOutcome) -> None:
        """Reset or deactivated: the worlds' goals end as `outcome`; they hold where they are."""
        self._read(sim)
        self._goals.abort(worlds, outcome)
        self._stop(worlds)
        self._timeline.pool.shrink()
        if self._pids is not None:
            self._pids.reset(worlds)

    def _stop(self, worlds: np.ndarray) -> None:
        """Drop the worlds' trajectories, running and queued, and hold them where they were
        measured at the last read."""
        self._timeline.stop(worlds, self.feedback_position[worlds])

    def _read(self, sim: Any) -> None:
        state = sim.state
        self.feedback_position[:] = state[:, self._pos_cols]
        if self._vel_cols is not None:
            self.feedback_velocity[:] = state[:, self._vel_cols]

    def update(self, sim: Any, time: float, period: float) -> None:
        self._read(sim)
        due = self._timeline.due(time)
        if due.size:
            self._start(due, time)
        self._timeline.sample(time)
        self._timeline.pool.shrink()
        self.error_position[:] = self.reference_position - self.feedback_position
        self.error_velocity[:] = self.reference_velocity - self.feedback_velocity
        if self._goals.checking:
            self._check_goals(sim, time)
        self._command(sim, period)

    def prepare(self, time: float) -> None:
        """The polynomials of the segments the worlds enter at the next update, made while the
        device steps (Timeline.prepare); under open_loop_control the first segments of the
        trajectories that start then too (they leave from the reference, known now)."""
        self._timeline.prepare(time, starts=self.open_loop)

    def _check_goals(self, sim: Any, time: float) -> None:
        """Goal outcomes of this update; a world whose goal was aborted for a violation holds."""
        errors = (
            self.error_position,
            self.error_velocity if self._velocity_error else None,
            self.reference_acceleration - sim.state[:, self._acc_cols] if self._acceleration_error else None,
        )
        hold = self._goals.check(time, self.executing, errors)
        if hold.size:
            self._stop(hold)
            self.error_position[hold] = 0.0
            self.error_velocity[hold] = -self.feedback_velocity[hold]

    def _start(self, due: np.ndarray, time: float) -> None:
        """Start the due worlds' queued trajectories from the current state, with their goals."""
        here = (self.reference_position if self.open_loop else self.feedback_position)[due]
        if self.open_loop:
            here_v = self.reference_velocity[due]
        elif self._vel_cols is not None:
            here_v = self.feedback_velocity[due]
        else:
            here_v = np.zeros((len(due), len(self.joints)))
        end, started = self._timeline.start(due, time, here, here_v)
        self._goals.start(due, end)
        if self._pids is not None:  # each trajectory integrates its own error
            self._pids.reset(started)

    def _command(self, sim: Any, period: float) -> None:
        if self._pids is not None:  # the velocity error is the error's derivative, as upstream's
            pid = self._pids.update(self.error_position, period, error_dot=self.error_velocity)
            u = self.ff_velocity_scale * self.reference_velocity + pid
            kind, cols = self._cmd[0]
            self.output[:] = u
            sim.command[:, cols] = u
            return
        for value, out, cols in self._writes:
            self.output[:, out] = value
            sim.command[:, cols] = value


def _order(kind: str) -> int:
    return (
        ("position", "velocity", "acceleration", "effort").index(kind)
        if kind in ("position", "velocity", "acceleration", "effort")
        else 99
    )
