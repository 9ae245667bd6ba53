"""A bridge worker: one rclpy context and node serving a contiguous range of worlds.

    python -m ros_bridge.worker ...   (ros_bridge/worker/process.py, started by host.py)

or, with `--bridge-workers 0`, the same `Worker` inside the physics process. It reads its
plan (ros_bridge/plan.py) once, attaches the shared memory, and then:

- per control period, woken by the loop (a byte on WAKE_FD, or a direct `tick()` in the
  physics process): copies its worlds' rows of the newest snapshot (seqlocked, so never a
  torn row), and publishes what is due to the worlds that have subscribers, built in bulk
  (ros_bridge/worker/messages.py); `/clock` from worker 0;
- on its executor thread (rclpy's EventsExecutor: per message, not per entity; intake.py bounds
  each world's topic): checks each command and writes it into its world's slots; trajectories are
  batched and handed over through its ring; rejections are counted per world, logged at
  most once per topic and reason every 2 s;
- serves services and actions: a request goes through the ring, the reply waits for the loop;
- now and then: re-reads subscriber counts (lazy publishing), scans the graph (topics
  created on request, commands to unknown actuators), publishes /diagnostics for its worlds.

The process exits when the physics process goes (WAKE_FD reaches EOF; the kernel also
sends SIGTERM through PR_SET_PDEATHSIG) or sends `q`.
"""

from __future__ import annotations

import contextlib
import os
import re
import select
import sys
import threading
import time as wallclock
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, ShutdownException
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64, Float64MultiArray

from batchsim.controllers.topics import MessageKind
from batchsim.memory import Memory, Ring
from batchsim.stamps import stamp_of
from ros_bridge.interfaces import available
from ros_bridge.naming import topic_name, worlds_label
from ros_bridge.options import Reliability
from ros_bridge.plan import FLAG_FROZEN, FleetPlan
from ros_bridge.protocol.commands import Problem, SlotWriter
from ros_bridge.protocol.demand import ChannelDemand
from ros_bridge.protocol.liveness import Beat, PhysicsWatch
from ros_bridge.protocol.snapshot import HEADERS, Snapshot, read_snapshot
from ros_bridge.throttle import LogThrottle
from ros_bridge.worker.command_callbacks import CommandCallbacks
from ros_bridge.worker.conflicts import check_conflicts
from ros_bridge.worker.diagnostics import Diagnostics
from ros_bridge.worker.graph_scan import GraphScan
from ros_bridge.worker.intake import Intake
from ros_bridge.worker.messages import MESSAGE_TYPES, clock_payload
from ros_bridge.worker.sensors import SensorPublishers
from ros_bridge.worker.services import LoopRequests, create_loop_services
from ros_bridge.worker.snapshot import Output
from ros_bridge.worker.trajectories import FLUSH_AFTER, TrajectoryIntake

SUBSCRIBER_REFRESH = 0.5  # s: subscriber counts re-read (lazy publishing)
DIAGNOSTICS_PERIOD = 0.5  # s
ACTION_POLL = 0.005  # s: while goals are in flight, their feedback and results wait at most this
CATCH_UP = 0.05  # s: a late worker's tick publishes missed snapshots this long, the rest at the next
_ACTUATOR_TOPIC = re.compile(r"^/(.+)/actuators/([^/]+)/command$")


class Worker:
    """Serves worlds `plan.ranges[index]` of `plan` on its own rclpy context and node.

    Args:
      plan: the fleet's plan.
      index: which worker (its range, node name, ring).
      memory: the shared arrays (attached, or the physics process's own).
      notify_fd: a pipe the loop waits on in lockstep; a byte is written when a command arrives.
    """

    def __init__(self, plan: FleetPlan, index: int, memory: Memory, *, notify_fd: int | None = None):
        self.plan = plan
        self.index = index
        self.lo, self.hi = plan.ranges[index]
        self.namespaces = plan.namespaces[self.lo : self.hi]
        self.memory = memory
        self.notify_fd = notify_fd
        os.environ.setdefault("RCUTILS_LOGGING_BUFFERED_STREAM", "0")  # log lines out as written, to files too
        self.context = Context()
        args = ["batchsim", "--ros-args", *plan.ros_args] if plan.ros_args else None  # the user's --ros-args
        rclpy.init(args=args, context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        try:
            self.node = Node(plan.node_names[index], context=self.context)
        except BaseException:
            rclpy.try_shutdown(context=self.context)
            raise
        self.logger = self.node.get_logger()
        self._graph = GraphScan(self.node, self._topic_seen, self._graph_seen)  # on request, unknown actuators
        self.throttle = LogThrottle(self.logger.warning)
        self.qos = QoSProfile(
            depth=plan.qos_depth,
            history=HistoryPolicy.KEEP_LAST,
            reliability=ReliabilityPolicy.BEST_EFFORT if plan.reliability is Reliability.BEST_EFFORT else ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.VOLATILE,
        )
        self.snapshot = Snapshot()
        self.commands = SlotWriter(memory, "cmd")
        self.ring = Ring(memory, f"ring{index}")
        self._ring_lock = threading.Lock()
        self.requests = LoopRequests(memory, index, self.ring, self._ring_lock, self._nudge)
        self.trajectories = TrajectoryIntake(plan, memory, self.ring, self._ring_lock, self._reject, self._nudge)
        self.callbacks = CommandCallbacks(plan, self.commands, self.trajectories, self._reject, self._nudge)
        self._outputs: list[Output] = []
        self._active: list[Output] = []  # outputs with a subscriber on some world
        self._beat = Beat(memory, index)
        self._demand = ChannelDemand(memory, "demand", index)
        self._running = False
        self._thread: threading.Thread | None = None
        self._due = {"refresh": 0.0, "diag": 0.0}
        self._clock_pub: Any = None
        self._last_clock = (-1, -1)
        self._clock_subscribers = 0
        self._last_done = -1
        self.diagnostics: Diagnostics | None = None
        self.published = 0  # messages published, for benchmarks
        self.sensors: SensorPublishers | None = None  # cameras and lidars (ros_bridge/worker/sensors.py)
        self.actions: Any = None  # FollowJointTrajectory servers (ros_bridge/worker/actions.py)
        self.type_check: Any = None  # remote endpoints of another definition (ros_bridge/worker/type_check.py)
        self.manager: Any = None  # controller_manager services (ros_bridge/worker/controller_manager.py)
        self.tf: Any = None  # tf, tf_static, robot_description (ros_bridge/worker/tf.py)
        self.controller_nodes: Any = None  # a node per controller (ros_bridge/worker/controller_nodes.py)
        self.simulation: Any = None  # mujoco_ros2_control's services (ros_bridge/worker/simulation.py)
        self._served: list[Any] = []

    # --- start ---
    def check_conflicts(self) -> tuple[str, str] | None:
        """Another process serving these worlds or /clock (ros_bridge/worker/conflicts.py)."""
        return check_conflicts(self.node, self.plan, self.index)

    def build(self) -> None:
        """Create what every world has from the start; the rest is created on request."""
        plan, node, qos = self.plan, self.node, self.qos
        if plan.clock and self.index == 0:
            self._clock_pub = node.create_publisher(Clock, "/clock", QoSProfile(depth=1))
        workers = [worlds_label(plan.namespaces, lo, hi) for lo, hi in plan.ranges]
        self.diagnostics = Diagnostics(node, self.memory, self.lo, self.hi, self.namespaces, workers, plan.robots)
        if self.index == 0:  # one worker says when the physics process stops (protocol/liveness.py)
            self.diagnostics.physics = PhysicsWatch(self.memory)
        self.intake = Intake(node, qos, lambda: self.snapshot.period, self.diagnostics, self.throttle)
        self._on_request: dict[str, tuple[Output, int]] = {}
        for spec in plan.outputs:
            out = Output(spec, self.namespaces)
            self._outputs.append(out)
            for row, ns in enumerate(self.namespaces):
                topic = topic_name(ns, spec.topic)
                if spec.on_request and not plan.all_topics:
                    self._on_request[topic] = (out, row)
                else:
                    out.publishers[row] = node.create_publisher(out.msg_type, topic, qos)

        interfaces, owners = plan.interfaces, plan.owners
        self._world_of = {ns: self.lo + row for row, ns in enumerate(self.namespaces)}
        self._actuators: dict[str, tuple[int, int]] = {}  # topic -> (world, column; -1 once subscribed)
        for row, ns in enumerate(self.namespaces):
            w = self.lo + row
            topic = topic_name(ns, "commands")
            self.intake.subscribe(w, Float64MultiArray, topic, self.callbacks.vector(w, topic, interfaces, owners))
            for robot, columns in zip(plan.robots, plan.robot_commands, strict=True):  # each robot's own vector
                topic = topic_name(ns, f"{robot}/commands")
                self.intake.subscribe(w, Float64MultiArray, topic, self.callbacks.vector(w, topic, interfaces, owners, columns))
            for c, (token, robot) in enumerate(zip(plan.actuator_topics, plan.actuator_robots, strict=True)):
                topic = topic_name(ns, f"{robot}actuators/{token}/command")
                if plan.all_topics:
                    self.intake.subscribe(w, Float64, topic, self.callbacks.single(w, c, topic, interfaces, owners))
                self._actuators[topic] = (w, -1 if plan.all_topics else c)
        self._actuator_list = ", ".join(plan.actuator_topics) or "none"

        for i, spec in enumerate(plan.inputs):
            msg_type = MESSAGE_TYPES[spec.kind]
            counter = self.memory[f"{spec.slots}.seq"]
            slots = None if spec.kind is MessageKind.JOINT_TRAJECTORY else SlotWriter(self.memory, spec.slots)
            for row, ns in enumerate(self.namespaces):
                w = self.lo + row
                topic = topic_name(ns, spec.topic)
                if slots is None:
                    callback = self.callbacks.trajectory(i, w, topic)
                else:
                    callback = self.callbacks.row(spec, slots, counter, w, topic)
                self.intake.subscribe(w, msg_type, topic, callback)

        if plan.tf is not None:  # the plan has one only where tf2_msgs is there
            from ros_bridge.worker.tf import TfPublishers

            self.tf = TfPublishers(node, plan.tf, self.namespaces, self.lo, all_topics=plan.all_topics)
        if plan.sensors is not None:
            self.sensors = SensorPublishers(
                node, qos, self.memory, plan.sensors, self.lo, self.hi, self.namespaces, plan.all_topics, self.diagnostics.missed,
                on_matched=self._refresh_now,
            )
        create_loop_services(
            node, self.requests, self.namespaces, self.lo, fleet=self.index == 0 and plan.fleet_services, robots=plan.robots
        )
        if plan.actions:  # the plan has them only where control_msgs is there
            from ros_bridge.worker.actions import ActionServers

            self.actions = ActionServers(
                node, plan.actions, self.memory, self.requests, self.namespaces, self.lo, self.index,
                self.trajectories.submit, lambda: self.snapshot.time,
            )  # fmt: skip
        if plan.manager is not None and available()["controller_manager_msgs"]:
            from ros_bridge.worker.controller_manager import ControllerManagerServices

            self.manager = ControllerManagerServices(
                node, plan.manager, self.memory, self.requests, self.namespaces, self.lo
            )
            if plan.controller_nodes:  # a node per controller and controller_manager, as ros2_control's
                from ros_bridge.worker.controller_nodes import ControllerNodes

                self.controller_nodes = ControllerNodes(
                    self.context, plan.manager, self.namespaces, self.requests, self.lo
                )
        if available()["mujoco_ros2_control_msgs"]:
            from ros_bridge.worker.simulation import SimulationServices

            self.simulation = SimulationServices(node, self.requests, plan, self.index)
        # per-world services and action servers created when a client appears (on_request.py)
        self._served = [s for s in (self.manager, self.actions, self.simulation) if s is not None]
        if plan.all_topics:
            for served in self._served:
                served.create_all()
        if any(available().values()):  # the types batchsim builds: a client of another definition is named
            from ros_bridge.worker.type_check import TypeCheck

            self.type_check = TypeCheck(node, (*(topic_name(ns, "") for ns in self.namespaces), "/tf"))

    def start(self) -> None:
        """Spin the executor on its own thread."""
        self.executor = EventsExecutor(context=self.context)
        self.executor.add_node(self.node)
        for side in self.controller_nodes.nodes if self.controller_nodes is not None else ():
            self.executor.add_node(side)
        # the EventsExecutor prints two lines to stdout for every timer beyond 8 on a clock
        # when it first takes them in, and every action server has one (rcl_action's goal
        # expiry): a fleet's hundreds would flood the console with them
        with _stdout_silenced():
            self.executor.spin_once(timeout_sec=0)
        self._running = True
        self._thread = threading.Thread(target=self._spin, name=f"ros_bridge_{self.index}", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop spinning and leave the ROS graph. Safe to call twice."""
        running, self._running = self._running, False
        self.requests.running = False
        if running and self._thread is not None:
            self._thread.join(timeout=2.0)
        if self.simulation is not None:
            self.simulation.close()
        if self.tf is not None:
            with contextlib.suppress(Exception):
                self.tf.close()
        if self.controller_nodes is not None:
            with contextlib.suppress(Exception):
                self.controller_nodes.close()
        with contextlib.suppress(Exception):
            self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)

    # --- the loop's side: once per period ---
    def serve(self, wake_fd: int) -> None:
        """Process mode: tick on every wake-up, and at least every 0.1 s, until EOF or `q`."""
        while True:
            ready, _, _ = select.select([wake_fd], [], [], 0.1)
            if ready:
                data = os.read(wake_fd, 4096)
                if not data or b"q" in data:
                    return
            self.tick()

    def tick(self) -> None:
        """Publish the newest snapshot if it is new; answer services; housekeeping."""
        self._beat.tick()
        until = wallclock.monotonic() + CATCH_UP
        for _ in range(HEADERS):  # woken late: each missed snapshot holding a channel, in order
            snap = read_snapshot(self.memory, len(self.plan.channels), self.lo, self.hi, self.snapshot, catch_up=True)
            if snap is None:
                break
            self._publish(snap)
            if self.actions is not None:
                self.actions.update(snap.channels, snap.time)
            if self.sensors is not None:  # between snapshots too: a camera's block holds its newest frame only
                self.sensors.publish()
            if wallclock.monotonic() > until:
                break  # services, the beat and housekeeping go on; the rest at the next tick
        if self.sensors is not None:
            self.sensors.publish()
        done = self.requests.tickets.done()
        if done != self._last_done:
            self._last_done = done
            self.requests.notify()
        now = wallclock.monotonic()
        due = self._due
        if now >= due["refresh"]:
            due["refresh"] = now + SUBSCRIBER_REFRESH
            self._refresh()
        self._graph.step(now)
        if self.actions is not None:
            self.actions.trim(now)
        if now >= due["diag"] and self.diagnostics.physics is not None:
            said = self.diagnostics.physics.check(wallclock.time())
            if said is not None:
                self.logger.warning(said)
        if now >= due["diag"] and self.snapshot.n >= 0:
            due["diag"] = now + DIAGNOSTICS_PERIOD
            self.diagnostics.publish(self.snapshot)
            self.throttle.flush()

    def _publish(self, snap: Snapshot) -> None:
        sec, nanosec = stamp_of(snap.time)
        # /clock only while someone listens (re-read with the other counts; a new subscriber
        # gets the time at once): a publish costs ~30 us, a period at 1 kHz has 1000
        if self._clock_subscribers and ((sec, nanosec) != self._last_clock or snap.forced):
            self._last_clock = (sec, nanosec)
            self._clock_pub.publish(clock_payload(sec, nanosec))
        for out in self._active:
            if snap.forced or snap.period % out.spec.every == 0:
                self._publish_rows(out, snap, out.rows, sec, nanosec, out.missed(snap))
        tf = self.tf
        if tf is not None and tf.wanted and tf.channel in snap.channels:
            self.published += tf.publish(snap.channels[tf.channel], sec, nanosec)

    def _publish_rows(self, out: Output, snap: Snapshot, rows: list[int], sec: int, nanosec: int, missed: int = 0) -> None:
        spec = out.spec
        if any(c not in snap.channels for c in spec.channels):
            return  # not copied this time (nobody wanted it until now)
        if spec.state and snap.flags.any():
            frozen = (snap.flags & FLAG_FROZEN) != 0
            rows = [r for r in rows if not frozen[r]]
        out.bulk.fill(out.values(snap.channels), sec, nanosec)
        pubs, payload = out.publishers, out.bulk.payload
        for r in rows:
            pubs[r].publish(payload(r))
        self.published += len(rows)
        self.diagnostics.published(spec.topic, rows, missed)

    def _refresh(self) -> None:
        """Lazy publishing: which rows have subscribers; which channels this worker needs.
        A world's first subscriber gets the newest state at once, so a node that waits for
        the state before it commands (lockstep) is not left waiting for the next period."""
        snap = self.snapshot
        sec, nanosec = stamp_of(snap.time)
        demand: set[int] = set()  # the channels this worker's subscribers and goals need
        active = []
        for out in self._outputs:
            before = set(out.rows)
            out.rows = [r for r, p in enumerate(out.publishers) if p is not None and p.get_subscription_count() > 0]
            if out.rows:
                active.append(out)
                demand.update(out.spec.channels)
                new = [r for r in out.rows if r not in before]
                if new and snap.n >= 0:
                    self._publish_rows(out, snap, new, sec, nanosec)
        self._active = active
        if self.sensors is not None:
            self.sensors.refresh()
        if self.tf is not None:
            self.tf.refresh()
            if self.tf.wanted:
                demand.add(self.tf.channel)
        if self.actions is not None:
            demand.update(self.actions.channels())
        self._demand.set(demand)
        if self._clock_pub is not None:
            count = self._clock_pub.get_subscription_count()
            if count > self._clock_subscribers and snap.n >= 0:
                self._clock_pub.publish(clock_payload(sec, nanosec))
            self._clock_subscribers = count

    def _refresh_now(self) -> None:
        """A publisher matched or lost a subscriber: read the counts at the next tick."""
        self._due["refresh"] = 0.0

    def _topic_seen(self, name: str) -> None:
        """The graph scan saw topic `name` (ros_bridge/worker/graph_scan.py): create an on-request
        publisher or actuator subscription someone asks for; reject commands to actuators this
        model does not have."""
        node = self.node
        if (
            (self.sensors is not None and self.sensors.requested(name))
            or (self.tf is not None and self.tf.requested(name))
            or (self.actions is not None and self.actions.requested(name))
        ):
            self._due["refresh"] = 0.0
            return
        hit = self._on_request.get(name)
        if hit is not None:
            if node.count_subscribers(name) > 0:
                out, row = hit
                out.publishers[row] = node.create_publisher(out.msg_type, name, self.qos)
                del self._on_request[name]
                self._due["refresh"] = 0.0
            return
        act = self._actuators.get(name)
        if act is not None:
            w, c = act
            if c >= 0 and node.count_publishers(name) > 0:
                callback = self.callbacks.single(w, c, name, self.plan.interfaces, self.plan.owners)
                self.intake.subscribe(w, Float64, name, callback)
                self._actuators[name] = (w, -1)  # subscribed
            return
        match = _ACTUATOR_TOPIC.match(name) if "/actuators/" in name else None
        if match is not None:
            w = self._world_of.get(match.group(1))
            if w is not None and node.count_publishers(name) > 0:
                self._reject(
                    w,
                    name,
                    Problem.UNKNOWN_ACTUATOR,
                    f"no actuator named {match.group(2)!r} in this model (actuators: {self._actuator_list})",
                )

    def _graph_seen(self, topics: list) -> None:
        """A pass over the graph's topics is through: services, then the type check."""
        if self._served:  # their services appear with a client
            for name, _types in self.node.get_service_names_and_types():
                if any(served.requested(name) for served in self._served):
                    self._due["refresh"] = 0.0
        if self.type_check is not None:
            self.type_check.scan(topics)

    # --- the executor thread ---
    def _spin(self) -> None:
        actions = self.actions
        while self._running:
            if any(served.pending for served in self._served):
                timeout = 0.0  # more to create: drain again at once
            elif self.trajectories.pending:
                timeout = FLUSH_AFTER
            elif actions is not None and actions.busy:
                timeout = ACTION_POLL  # feedback and results the loop thread queued
            else:
                timeout = 0.1
            try:
                self.executor.spin_once(timeout_sec=timeout)
                for served in self._served:
                    served.drain()
            except (ExternalShutdownException, ShutdownException):
                break
            except Exception as e:  # a failing callback must not end the worker
                if not self._running or not self.context.ok():
                    break
                self.throttle.warn(("callback", type(e).__name__), f"ROS callback failed: {type(e).__name__}: {e}")
            if self.trajectories.due():
                self.trajectories.flush()
            self.intake.service()

    def _nudge(self) -> None:
        """Lockstep: tell the loop a command arrived (a full pipe: it has been told already)."""
        if self.notify_fd is not None:
            with contextlib.suppress(BlockingIOError, OSError):
                os.write(self.notify_fd, b"c")

    def _reject(self, world: int, topic: str, problem: Problem, reason: str) -> None:
        self.diagnostics.reject(world, self.snapshot.period, topic, problem, reason)
        self.throttle.warn((topic, problem), f"rejected command on {topic}: {reason}")


@contextlib.contextmanager
def _stdout_silenced():
    """File descriptor 1 points at /dev/null for the duration (C++ writes too)."""
    sys.stdout.flush()
    saved, null = os.dup(1), os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(null)
