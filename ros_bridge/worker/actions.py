"""The actions of every world of a worker: FollowJointTrajectory on every trajectory
controller, GripperCommand on every gripper action controller.

GripperCommand (`/<ns>/<controller>/gripper_cmd`): a goal goes to the loop as one
GRIPPER_GOAL request; the controller decides each world's outcome as upstream's
gripper_action_controller (batchsim/controllers/gripper.py): SUCCEEDED with reached_goal,
a stall SUCCEEDED or ABORTED by `allow_stalling`, a cancel CANCELED where it holds.

`/<ns>/<controller>/follow_joint_trajectory` (control_msgs/action/FollowJointTrajectory),
served as ros2_controllers' JointTrajectoryController serves it:

- each world's server is created when an action client for it appears in the ROS graph
  (scanned every second), or all at start with `--all-topics`;
- a goal for a world where the controller is inactive is rejected (as upstream);
- an accepted goal is checked here first: no joint names, an unknown or repeated joint, a
  tolerance naming a joint the controller lacks -> INVALID_JOINTS; a stamped trajectory
  that ends before the current sim time -> OLD_HEADER_TIMESTAMP; a goal the controller
  refuses (NaN, times not increasing, limits: its reason) -> INVALID_GOAL. Such a goal is
  aborted at once with that code and an error string naming the problem (upstream rejects
  it without a reason; the codes exist for this);
- a valid goal goes to the loop with the topic's trajectories, as one batch, tagged, with
  its path and goal tolerances and goal_time_tolerance; the controller checks them in
  every world at once (batchsim/controllers/trajectory/goals.py);
- at the action monitor rate (20 Hz, upstream's default) the worker reads each world's
  goal tag, outcome and desired/actual/error from a snapshot channel: feedback while the
  goal runs; SUCCEEDED (SUCCESSFUL), or ABORTED with PATH_TOLERANCE_VIOLATED or
  GOAL_TOLERANCE_VIOLATED naming the joint; a cancel request goes to the loop and the goal
  ends CANCELED once the world holds; a newer goal or a topic trajectory for the world
  ends the old goal ABORTED with INVALID_GOAL ("Current goal cancelled due to new incoming
  action.", upstream's words; rclpy has no way from executing to canceled without a
  cancel request); a reset world's goal is ABORTED.
"""

from __future__ import annotations

import collections
import ctypes
import dataclasses
import threading
import time as wallclock
from collections.abc import Callable
from typing import Any

import numpy as np
from action_msgs.msg import GoalStatus, GoalStatusArray
from control_msgs.action import FollowJointTrajectory, GripperCommand
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.node import Node
from rclpy.qos import qos_profile_action_status_default
from rclpy.task import Future

from batchsim.controllers.joint_names import JointOrder
from batchsim.controllers.topics import GoalOutcome
from batchsim.memory import Memory
from batchsim.stamps import stamp_of
from ros_bridge.action_plan import (
    STATUS_COLUMNS,
    GripperActionSpec,
    TrajectoryActionSpec,
    encode_cancel,
    encode_gripper_goal,
)
from ros_bridge.naming import topic_name
from ros_bridge.protocol.active import ActiveReader
from ros_bridge.protocol.demand import ChannelDemand
from ros_bridge.protocol.goals import RefusalReader, held, hold, release
from ros_bridge.protocol.requests import Kind
from ros_bridge.worker.messages import Trajectory, parse_trajectory, seconds
from ros_bridge.worker.on_request import OnRequest
from ros_bridge.worker.services import GOAL_RATE, LoopRequests

FJT = FollowJointTrajectory.Result
_ACTION_NAME = {TrajectoryActionSpec: "follow_joint_trajectory", GripperActionSpec: "gripper_cmd"}
UNSEEN_TIMEOUT = 5.0  # s a goal may wait to show up in its world before it is given up
PREEMPTED = "Current goal cancelled due to new incoming action."  # upstream's words
RESULT_TIMEOUT = 60.0  # s a finished goal's result (and its request) is kept for a client to fetch
BIG_GOAL = 100_000  # trajectory points: a goal larger is rejected at once and the worker trims its heap
TRIM_EVERY = 5.0  # s between two trims while one may free pages


def _malloc_trim() -> None:
    """glibc's malloc_trim(0): free heap pages back to the system (elsewhere: nothing)."""
    try:
        ctypes.CDLL(None).malloc_trim(0)
    except (OSError, AttributeError):
        pass


@dataclasses.dataclass
class _Goal:
    handle: Any
    tag: int
    world: int
    action: int
    future: Future
    since: float
    seen: bool = False  # the controller has shown its tag
    cancel_sent: bool = False


class ActionServers(OnRequest):
    """The action servers of worlds [lo, lo + len(namespaces)), one per action and world.

    Args:
      submit: `submit(input_index, world, parsed trajectory, goal)`, the worker's way of
        handing a trajectory to the loop; goal = (tag, path (njoint, 3), goal (njoint, 3),
        goal_time_tolerance).
      time: the newest sim time the worker has seen.
    """

    def __init__(
        self,
        node: Node,
        specs: list[TrajectoryActionSpec | GripperActionSpec],
        memory: Memory,
        requests: LoopRequests,
        namespaces: list[str],
        lo: int,
        index: int,
        submit: Callable[[int, int, tuple, tuple], None],
        time: Callable[[], float],
    ):
        super().__init__()
        self.specs = specs
        self.requests = requests
        self.logger = node.get_logger()
        self.active = ActiveReader(memory)
        self.refusals = RefusalReader(memory)
        self.demand = ChannelDemand(memory, "demand", index)  # the channels the loop copies for this worker
        self.submit = submit
        self.time = time
        self.lo = lo
        self._tag = index << 40  # tags unique across the fleet's workers
        self._lock = threading.Lock()
        self.inflight: list[dict[int, _Goal]] = [{} for _ in specs]  # per action: world -> goal
        self._handles: dict[int, _Goal] = {}  # accepted goals until their execute callback runs
        self._trim_until = self._next_trim = 0.0  # while a big goal's objects may be freed (trim)
        # what the loop thread decided, carried out on the executor thread (the worker's spin
        # loop calls drain()): rclpy's goal handles are not safe to drive from two threads
        # (feedback from one deadlocked a state change on the other), and the EventsExecutor
        # takes no guard condition to wake it
        self._queue: collections.deque[tuple[_Goal, Any, Any]] = collections.deque()
        self._servers = []
        self._node = node
        # per world and action, created when a client appears in the ROS graph (on_request.py):
        # five endpoints per action and world
        for a, spec in enumerate(specs):
            for row, ns in enumerate(namespaces):
                self.offer(topic_name(ns, f"{spec.controller}/{_ACTION_NAME[type(spec)]}"), (a, lo + row))
        self.memory = memory
        self._told = self._tell_predecessors_goals(node, namespaces)

    def _tell_predecessors_goals(self, node: Node, namespaces: list[str]) -> list[Any]:
        """A restarted worker: the goals its predecessor had accepted and not finished never get
        their result; their clients are told ABORTED on each action's status topic (latched, as
        an action server's own). Returns the publishers, kept for late subscribers."""
        publishers = []
        for world, a, goal_id in held(self.memory, self.lo, self.lo + len(namespaces)):
            spec = self.specs[a]
            action = topic_name(namespaces[world - self.lo], f"{spec.controller}/{_ACTION_NAME[type(spec)]}")
            status = GoalStatus(status=GoalStatus.STATUS_ABORTED)
            status.goal_info.goal_id.uuid = list(goal_id)
            pub = node.create_publisher(GoalStatusArray, f"{action}/_action/status", qos_profile_action_status_default)
            pub.publish(GoalStatusArray(status_list=[status]))
            publishers.append(pub)
            release(self.memory, world, a, goal_id)
            self.logger.error(
                f"{spec.controller} in world {world}: a goal in flight when the bridge worker serving it stopped "
                "is told ABORTED on the action's status topic (its result was lost with that worker)"
            )
        return publishers

    def base_of(self, name: str) -> str | None:
        """An action client's topics and services are `<action>/_action/...`."""
        return name.partition("/_action/")[0] if "/_action/" in name else None

    def _create(self, action: str, hit: tuple[int, int]) -> None:
        a, w = hit
        kind = FollowJointTrajectory if isinstance(self.specs[a], TrajectoryActionSpec) else GripperCommand
        self._servers.append(
            ActionServer(
                self._node,
                kind,
                action,
                execute_callback=self._execute,
                goal_callback=lambda request: self._goal(a, w, request),
                result_timeout=RESULT_TIMEOUT,
                handle_accepted_callback=lambda handle: self._accepted(a, w, handle),
                cancel_callback=lambda handle: self._cancel(a, w, handle),
            )
        )

    def channels(self) -> list[int]:
        """The snapshot channels this worker needs now (actions with a goal in flight)."""
        return [spec.channel for spec, goals in zip(self.specs, self.inflight, strict=True) if goals]

    # --- the executor thread ---
    def _goal(self, a: int, world: int, request: Any) -> GoalResponse:
        spec = self.specs[a]
        points = len(getattr(getattr(request, "trajectory", None), "points", ()))
        if points > BIG_GOAL:  # its Python objects: hundreds of MB, freed when it is rejected or its result expires
            self._trim_until = wallclock.monotonic() + RESULT_TIMEOUT + 2 * TRIM_EVERY
        if not self.requests.admit(world, rate=GOAL_RATE):  # one world's flood of goals: its neighbours' go first
            message, log = self.requests.refusal(f"{spec.controller} in world {world}: goal")
            if log:
                self.logger.error(message)
            return GoalResponse.REJECT
        if points > BIG_GOAL and 0 < spec.max_points < points:  # accepted, it would be kept until then
            self.logger.error(
                f"{spec.controller} in world {world}: goal rejected: {points} points, more than {spec.max_points}"
                f" (a goal of more than {BIG_GOAL} is rejected at once, not kept for its result)"
            )
            return GoalResponse.REJECT
        if not self.active.active(world, spec.controller_index):
            self.logger.error(f"{spec.controller} in world {world}: can't accept new action goals: controller is not running")
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def _accepted(self, a: int, world: int, handle: Any) -> None:
        spec = self.specs[a]
        with self._lock:
            self._tag += 1
            goal = _Goal(handle, self._tag, world, a, Future(), wallclock.monotonic())
        self._handles[id(handle)] = goal
        request = handle.request
        if isinstance(spec, TrajectoryActionSpec):
            parsed = _parse_goal(spec, request, self.time())
            if not isinstance(parsed, _TrajectoryGoal):
                code, problem = parsed
                self.logger.error(f"{spec.controller} in world {world}: goal aborted: {problem}")
                goal.future.set_result((GoalOutcome.ABORTED, FJT(error_code=code, error_string=problem)))
                handle.execute()
                return
        hold(self.memory, world, a, bytes(handle.goal_id.uuid))  # for a worker that follows this one
        with self._lock:
            old = self.inflight[a].get(world)
            self.inflight[a][world] = goal
        self.demand.add(spec.channel)  # at once: the worker's refresh re-reads demand only twice a second
        if old is not None:  # preempted, as upstream's preempt_active_goal
            self._finish(old, GoalOutcome.ABORTED, self._result(old, FJT.INVALID_GOAL, PREEMPTED))
        if isinstance(spec, TrajectoryActionSpec):
            self.submit(spec.input, world, parsed.trajectory, (goal.tag, parsed.path, parsed.final, parsed.goal_time))
        else:
            command = request.command
            encoded = encode_gripper_goal(a, world, goal.tag, float(command.position), float(command.max_effort))
            if self.requests.put(Kind.GRIPPER_GOAL, lambda t: encoded) is None:
                self._finish(goal, GoalOutcome.ABORTED, self._result(goal, FJT.INVALID_GOAL, "the loop is too far behind"))
        handle.execute()

    def _cancel(self, a: int, world: int, handle: Any) -> CancelResponse:
        goal = self.inflight[a].get(world)
        if goal is None or goal.handle is not handle:
            return CancelResponse.REJECT
        if not goal.cancel_sent:
            goal.cancel_sent = True
            self.requests.put(Kind.CANCEL, lambda t: encode_cancel(a, world, goal.tag))
        return CancelResponse.ACCEPT

    async def _execute(self, handle: Any) -> Any:
        goal = self._handles.pop(id(handle))
        outcome, result = await goal.future
        if outcome is GoalOutcome.SUCCEEDED:
            handle.succeed()
        elif outcome is GoalOutcome.CANCELED and handle.is_cancel_requested:
            handle.canceled()
        else:
            handle.abort()
        return result

    # --- the worker's loop thread ---
    def update(self, channels: dict[int, np.ndarray], time: float) -> None:
        """Feedback and outcomes from the snapshot's action channels (the rows of this worker)."""
        self._decide(channels, time)

    def _decide(self, channels: dict[int, np.ndarray], time: float) -> None:
        now = wallclock.monotonic()
        stamp = stamp_of(time)
        for a, spec in enumerate(self.specs):
            goals = self.inflight[a]
            values = channels.get(spec.channel)
            if not goals or values is None:
                continue
            for world, goal in list(goals.items()):
                row = values[world - self.lo]
                if int(row[0]) != goal.tag:
                    refusal = self.refusals.refused(world, goal.tag)
                    if refusal is not None:
                        self._finish(goal, GoalOutcome.ABORTED, self._result(goal, FJT.INVALID_GOAL, refusal[1], row))
                    elif goal.seen:
                        text = "replaced by a command on the controller's topic"
                        self._finish(goal, GoalOutcome.ABORTED, self._result(goal, FJT.INVALID_GOAL, text, row))
                    elif now - goal.since > UNSEEN_TIMEOUT:
                        text = "the simulation loop did not take the goal"
                        self._finish(goal, GoalOutcome.ABORTED, self._result(goal, FJT.INVALID_GOAL, text, row))
                    continue
                goal.seen = True
                outcome = GoalOutcome(int(row[1]))
                if outcome is GoalOutcome.ACTIVE:
                    self._queue.append((goal, None, self._feedback(spec, row, stamp)))
                elif isinstance(spec, TrajectoryActionSpec):
                    self._finish(goal, *_trajectory_outcome(spec, outcome, int(row[2])))
                else:
                    final = GoalOutcome.ABORTED if outcome is GoalOutcome.NONE else outcome
                    self._finish(goal, final, self._result(goal, 0, "", row))

    def _result(self, goal: _Goal, code: int, text: str, row: np.ndarray | None = None) -> Any:
        """The action's result: FollowJointTrajectory's code and text, or GripperCommand's state."""
        if isinstance(self.specs[goal.action], TrajectoryActionSpec):
            return FJT(error_code=code, error_string=text)
        result = GripperCommand.Result()
        if row is not None:
            result.stalled, result.reached_goal = bool(row[2]), bool(row[3])
            result.position, result.effort = float(row[4]), float(np.nan_to_num(row[5]))
        return result

    def _feedback(self, spec: TrajectoryActionSpec | GripperActionSpec, row: np.ndarray, stamp: tuple[int, int]) -> Any:
        if isinstance(spec, GripperActionSpec):
            return GripperCommand.Feedback(
                position=float(row[4]), effort=float(np.nan_to_num(row[5])), stalled=bool(row[2]), reached_goal=bool(row[3])
            )
        nj = len(spec.joints)
        fb = FollowJointTrajectory.Feedback()
        fb.header.stamp.sec, fb.header.stamp.nanosec = stamp
        fb.joint_names = list(spec.joints)
        parts = [row[STATUS_COLUMNS + k * nj : STATUS_COLUMNS + (k + 1) * nj] for k in range(6)]
        for point, (p, v) in zip((fb.desired, fb.actual, fb.error), (parts[0:2], parts[2:4], parts[4:6]), strict=True):
            point.positions, point.velocities = p.tolist(), v.tolist()
        return fb

    def _finish(self, goal: _Goal, outcome: GoalOutcome, result: Any) -> None:
        """The goal is over: out of flight now, its result set on the executor thread."""
        with self._lock:
            if self.inflight[goal.action].get(goal.world) is goal:
                del self.inflight[goal.action][goal.world]
        release(self.memory, goal.world, goal.action, bytes(goal.handle.goal_id.uuid))
        self._queue.append((goal, outcome, result))

    @property
    def busy(self) -> bool:
        """Goals in flight or decisions waiting: the spin loop should come back soon."""
        return bool(self._queue) or any(self.inflight) or bool(self._handles) or bool(self._to_create)

    def trim(self, now: float) -> None:
        """Give the heap's free pages back to the system every TRIM_EVERY s while a big goal's
        objects may still be freed (its result expiring): Python frees them, but glibc keeps the
        pages of a heap it grew (a 1,000,000-point goal: 700-800 MB, kept for good before)."""
        if now < self._trim_until and now >= self._next_trim:
            self._next_trim = now + TRIM_EVERY
            _malloc_trim()

    def drain(self) -> None:
        """The executor thread: servers created; feedback published and results handed to the goals'
        execute callbacks."""
        super().drain()
        while self._queue:
            goal, outcome, payload = self._queue.popleft()
            if outcome is None:
                if not goal.future.done():
                    goal.handle.publish_feedback(payload)
            elif not goal.future.done():
                goal.future.set_result((outcome, payload))


def _trajectory_outcome(spec: TrajectoryActionSpec, outcome: GoalOutcome, joint: int) -> tuple[GoalOutcome, Any]:
    """A finished FollowJointTrajectory goal's state and result, from the controller's outcome."""
    name = spec.joints[joint] if 0 <= joint < len(spec.joints) else "?"
    if outcome is GoalOutcome.SUCCEEDED:
        return outcome, FJT(error_code=FJT.SUCCESSFUL)
    if outcome is GoalOutcome.PATH_TOLERANCE_VIOLATED:
        return GoalOutcome.ABORTED, FJT(error_code=FJT.PATH_TOLERANCE_VIOLATED, error_string=f"joint {name!r} left its path tolerance")
    if outcome is GoalOutcome.GOAL_TOLERANCE_VIOLATED:
        text = f"joint {name!r} is outside its goal tolerance"
        return GoalOutcome.ABORTED, FJT(error_code=FJT.GOAL_TOLERANCE_VIOLATED, error_string=text)
    if outcome is GoalOutcome.CANCELED:
        return outcome, FJT(error_code=FJT.SUCCESSFUL, error_string="canceled")
    if outcome is GoalOutcome.DEACTIVATED:  # upstream's words (JointTrajectoryController::on_deactivate)
        return GoalOutcome.ABORTED, FJT(error_code=FJT.INVALID_GOAL, error_string="Current goal cancelled during deactivate transition.")
    return GoalOutcome.ABORTED, FJT(error_code=FJT.INVALID_GOAL, error_string="the world was reset")


@dataclasses.dataclass(frozen=True)
class _TrajectoryGoal:
    """A FollowJointTrajectory goal as the loop takes it."""

    trajectory: Trajectory  # in the message's joint order (TrajectoryIntake maps it)
    path: np.ndarray  # (njoint, 3) path tolerances, the controller's joint order (0: its default)
    final: np.ndarray  # (njoint, 3) goal tolerances, likewise
    goal_time: float  # goal_time_tolerance, s


def _parse_goal(spec: TrajectoryActionSpec, request: Any, time: float) -> _TrajectoryGoal | tuple[int, str]:
    """A FollowJointTrajectory goal, parsed once; or (upstream's error code, the problem)."""
    order = JointOrder(spec.joints)
    names = list(request.trajectory.joint_names)
    if not names:
        return FJT.INVALID_JOINTS, "empty joint_names on the goal's trajectory"
    problem = order.problem(names)
    if problem is not None:
        return FJT.INVALID_JOINTS, problem
    tables = []
    for what, tolerances in (("path_tolerance", request.path_tolerance), ("goal_tolerance", request.goal_tolerance)):
        table = np.zeros((len(order), 3))
        for t in tolerances:
            column = order.column(t.name)
            if column is None:
                return FJT.INVALID_JOINTS, f"{what} names joint {t.name!r}, which the controller does not have"
            values = (t.position, t.velocity, t.acceleration)
            if not all(np.isfinite(values)):
                return FJT.INVALID_GOAL, f"{what} of joint {t.name!r} is not finite"
            table[column] = values
        tables.append(table)
    if spec.max_points and len(request.trajectory.points) > spec.max_points:
        return FJT.INVALID_GOAL, f"{len(request.trajectory.points)} points, more than {spec.max_points}"
    try:
        trajectory = parse_trajectory(request.trajectory)
    except (ValueError, TypeError) as e:
        return FJT.INVALID_GOAL, str(e)
    times, start = trajectory[1], trajectory[5]
    if start != 0.0 and len(times):
        end = start + float(times[-1])
        if end < time:
            return (
                FJT.OLD_HEADER_TIMESTAMP,
                f"the trajectory starts at {start:.3f} s and ends at {end:.3f} s, before the sim time {time:.3f} s",
            )
    return _TrajectoryGoal(trajectory, *tables, seconds(request.goal_time_tolerance))
