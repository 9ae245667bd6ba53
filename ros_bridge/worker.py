"""A bridge worker: one rclpy context and node serving a contiguous range of worlds.

    python -m ros_bridge.worker INDEX WAKE_FD STATUS_FD NOTIFY_FD [--check]   (started by host.py)

or, with `--bridge-workers 0`, the same `Worker` inside the physics process. It reads its
plan (ros_bridge/plan.py) once, attaches the shared memory, and then:

- per control period, woken by the loop (a byte on WAKE_FD, or a direct `tick()` in the
  physics process): copies its worlds' rows of the newest snapshot (seqlocked, so never a
  torn row), and publishes what is due to the worlds that have subscribers, built in bulk
  (ros_bridge/messages.py); `/clock` from worker 0;
- on its executor thread (rclpy's EventsExecutor: per message, not per entity): checks
  each command and writes it into its world's slots in shared memory; trajectories are
  batched and handed over through its ring; rejections are counted per world, logged at
  most once per topic and reason every 2 s;
- serves the per-world `reset` services, and worker 0 `/batchsim/{reset,pause,step}`:
  each request goes through the ring with a ticket; the reply waits until the loop has
  carried it out;
- now and then: re-reads subscriber counts (lazy publishing), scans the graph (topics
  created on request, commands to unknown actuators), publishes /diagnostics for its worlds.

The process exits when the physics process goes (WAKE_FD reaches EOF; the kernel also
sends SIGTERM through PR_SET_PDEATHSIG) or sends `q`.
"""

from __future__ import annotations

import ctypes
import os
import pickle
import re
import select
import signal
import sys
import threading
import time as wallclock
from collections.abc import Callable
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, ShutdownException
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64, Float64MultiArray
from std_srvs.srv import SetBool, Trigger

from batchsim.controllers.topics import MessageKind, trajectory_batch
from batchsim.hardware import Status
from batchsim.memory import Memory, Ring
from ros_bridge.commands import Problem, RejectionWriter, SlotWriter, check_single, check_vector
from ros_bridge.messages import (
    MESSAGE_TYPES,
    BulkMessages,
    clock_payload,
    message_type,
    parse_row,
    parse_trajectory,
    stamp_of,
)
from ros_bridge.options import Reliability
from ros_bridge.plan import FLAG_BAD, FLAG_FROZEN, FLAG_TIMED_OUT, FleetPlan, OutputSpec
from ros_bridge.requests import Kind, encode_reset, encode_ticket, encode_trajectories
from ros_bridge.sensor_worker import SensorPublishers
from ros_bridge.throttle import LogThrottle

SUBSCRIBER_REFRESH = 0.5  # s: subscriber counts re-read (lazy publishing)
GRAPH_SCAN = 1.0  # s: topics created on request, commands to unknown actuators
DIAGNOSTICS_PERIOD = 0.5  # s
SERVICE_WAIT = 2.0  # s a service waits for the loop to carry out its request
FLUSH_AFTER = 0.001  # s: trajectories reach the loop this long after they arrive, at most
_ACTUATOR_TOPIC = re.compile(r"^/(.+)/actuators/([^/]+)/command$")


class _Output:
    """One OutputSpec over this worker's worlds: publishers (None until created), bulk bytes."""

    def __init__(self, spec: OutputSpec, namespaces: list[str]):
        self.spec = spec
        self.namespaces = namespaces
        self._bulk: BulkMessages | None = None
        self.publishers: list[Any] = [None] * len(namespaces)
        self.rows: list[int] = []  # the worlds (rows) with a subscriber
        self.msg_type = message_type(spec.msg_type)
        # per field: (channel, columns with -1 clipped, the columns that are -1)
        self.gather = [
            (f.channel, np.maximum(np.array(f.columns, dtype=np.intp), 0), np.array(f.columns) < 0) for f in spec.fields
        ]

    @property
    def bulk(self) -> BulkMessages:
        """The serialized messages, laid out when first published (most outputs never are)."""
        if self._bulk is None:
            self._bulk = BulkMessages(self.spec, self.namespaces)
        return self._bulk

    def values(self, channels: dict[int, np.ndarray]) -> np.ndarray:
        parts = []
        for ch, cols, nan in self.gather:
            v = channels[ch][:, cols]
            if nan.any():
                v[:, nan] = np.nan
            parts.append(v)
        return np.concatenate(parts, axis=1) if len(parts) > 1 else parts[0]


class Snapshot:
    """This worker's rows of one snapshot, copied out of shared memory."""

    __slots__ = ("n", "period", "time", "forced", "status", "flags", "channels", "written")

    def __init__(self) -> None:
        self.n = -1
        self.period = 0
        self.time = 0.0
        self.forced = False
        self.status = np.zeros(0, np.uint8)
        self.flags = np.zeros(0, np.uint8)
        self.channels: dict[int, np.ndarray] = {}
        self.written = np.zeros(0, np.int64)


class Worker:
    """Serves worlds `plan.ranges[index]` of `plan` on its own rclpy context and node.

    Args:
      plan: the fleet's plan.
      index: which worker (its range, node name, ring).
      memory: the shared arrays (attached, or the physics process's own).
      notify_fd: a pipe the loop waits on in lockstep; a byte is written when a command arrives.
      log: where the worker's own lines go (its node's logger by default).
    """

    def __init__(self, plan: FleetPlan, index: int, memory: Memory, *, notify_fd: int | None = None):
        self.plan = plan
        self.index = index
        self.lo, self.hi = plan.ranges[index]
        self.namespaces = plan.namespaces[self.lo : self.hi]
        self.memory = memory
        self.notify_fd = notify_fd
        # log lines go out as they are written, also when stderr is a file or a pipe
        os.environ.setdefault("RCUTILS_LOGGING_BUFFERED_STREAM", "0")
        self.context = Context()
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        try:
            self.node = Node(plan.node_names[index], context=self.context)
        except BaseException:
            rclpy.try_shutdown(context=self.context)
            raise
        self.logger = self.node.get_logger()
        self.throttle = LogThrottle(self.logger.warning)
        self.qos = QoSProfile(
            depth=plan.qos_depth,
            history=HistoryPolicy.KEEP_LAST,
            reliability=(
                ReliabilityPolicy.BEST_EFFORT if plan.reliability is Reliability.BEST_EFFORT else ReliabilityPolicy.RELIABLE
            ),
            durability=DurabilityPolicy.VOLATILE,
        )
        self.snapshot = Snapshot()
        self.commands = SlotWriter(memory, "cmd")
        self.rejections = RejectionWriter(memory, "rej")
        self.host_rejections = RejectionWriter(memory, "hrej")
        self.ring = Ring(memory, f"ring{index}")
        self._ring_lock = threading.Lock()
        self._service_cond = threading.Condition()
        self._pending: dict[int, list] = {}  # trajectory input -> [(world, parsed...)]
        self._pending_since = 0.0
        self._pending_lock = threading.Lock()
        self._outputs: list[_Output] = []
        self._active: list[_Output] = []  # outputs with a subscriber on some world
        self._beat = memory["beat"]
        self._svc_done = memory["svc.done"]
        self._subscriptions: list[Any] = []
        self._running = False
        self._thread: threading.Thread | None = None
        self._due = {"refresh": 0.0, "scan": 0.0, "diag": 0.0}
        self._clock_pub: Any = None
        self._diag_pub: Any = None
        self._last_clock = (-1, -1)
        self._clock_subscribers = 0
        self._last_done = -1
        # per world (row): rejections per (topic, reason), for /diagnostics
        self._rejected: list[dict[tuple[str, str], int]] = [{} for _ in self.namespaces]
        self._rejected_lock = threading.Lock()
        self._host_seen = self.host_rejections.count[self.lo : self.hi].copy()
        self.published = 0  # messages published, for benchmarks
        self.sensors: SensorPublishers | None = None  # cameras and lidars (ros_bridge/sensor_worker.py)

    # --- start ---
    def check_conflicts(self) -> tuple[str, str] | None:
        """Watch the graph for `plan.startup_check` s: another process that serves one of
        these namespaces, or a /clock publisher when this process would publish one too.
        Returns (kind, message) with kind "namespace" or "clock", or None."""
        plan = self.plan
        if os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").upper() in ("LOCALHOST", "OFF"):
            return None  # no other host can join: the host's registry (registry.py) has seen every fleet
        mine = {f"/{ns}/reset" for ns in plan.namespaces}
        own = plan.node_names[self.index]
        deadline = wallclock.monotonic() + plan.startup_check
        extended = False
        while True:
            unresolved = False
            names = self.node.get_node_names_and_namespaces()
            seen_own = False
            for name, ns in names:
                if not name.startswith("batchsim"):
                    continue
                if name == own and ns == "/" and not seen_own:
                    seen_own = True  # this node; another of the same name is another process's
                    continue
                services = [s for s, _ in self.node.get_service_names_and_types_by_node(name, ns)]
                if not any(s.endswith("/reset") for s in services):
                    unresolved = True  # the node is known, its worlds' services not yet
                    continue
                clash = sorted(s for s in services if s in mine)
                if clash:
                    where = clash[0].rsplit("/", 1)[0]
                    more = f" and {len(clash) - 1} more" if len(clash) > 1 else ""
                    return (
                        "namespace",
                        f"another batchsim process already serves {where}{more} (node {_full(ns, name)}): "
                        "give this one other worlds (a world offset or another namespace template) or another "
                        "ROS domain (a process killed outright stays in the ROS graph for up to 20 s)",
                    )
            if plan.clock:
                for info in self.node.get_publishers_info_by_topic("/clock"):
                    return (
                        "clock",
                        f"another process already publishes /clock (node {_full(info.node_namespace, info.node_name)}): "
                        "only one process of a fleet may",
                    )
            now = wallclock.monotonic()
            if now >= deadline:
                if unresolved and not extended:
                    deadline, extended = now + 4.0, True
                    continue
                return None
            wallclock.sleep(0.1)

    def build(self) -> None:
        """Create what every world has from the start; the rest is created on request."""
        plan, node, qos = self.plan, self.node, self.qos
        if plan.clock and self.index == 0:
            self._clock_pub = node.create_publisher(Clock, "/clock", QoSProfile(depth=1))
        self._diag_pub = node.create_publisher(DiagnosticArray, "/diagnostics", QoSProfile(depth=10))
        self._on_request: dict[str, tuple[_Output, int]] = {}
        for spec in plan.outputs:
            out = _Output(spec, self.namespaces)
            self._outputs.append(out)
            for row, ns in enumerate(self.namespaces):
                topic = f"/{ns}/{spec.topic}"
                if spec.on_request and not plan.all_topics:
                    self._on_request[topic] = (out, row)
                else:
                    out.publishers[row] = node.create_publisher(out.msg_type, topic, qos)

        interfaces, owners = plan.interfaces, plan.owners
        self._world_of = {ns: self.lo + row for row, ns in enumerate(self.namespaces)}
        self._actuators: dict[str, tuple[int, int]] = {}  # topic -> (world, column; -1 once subscribed)
        for row, ns in enumerate(self.namespaces):
            w = self.lo + row
            topic = f"/{ns}/commands"
            self._subscribe(Float64MultiArray, topic, self._vector_callback(w, topic, interfaces, owners))
            for c, token in enumerate(plan.actuator_topics):
                topic = f"/{ns}/actuators/{token}/command"
                if plan.all_topics:
                    self._subscribe(Float64, topic, self._single_callback(w, c, topic, interfaces, owners))
                self._actuators[topic] = (w, -1 if plan.all_topics else c)
        self._actuator_list = ", ".join(plan.actuator_topics) or "none"

        for i, spec in enumerate(plan.inputs):
            msg_type = MESSAGE_TYPES[spec.kind]
            counter = self.memory[f"{spec.slots}.seq"]
            slots = None if spec.kind is MessageKind.JOINT_TRAJECTORY else SlotWriter(self.memory, spec.slots)
            for row, ns in enumerate(self.namespaces):
                w = self.lo + row
                topic = f"/{ns}/{spec.topic}"
                if slots is None:
                    callback = self._trajectory_callback(i, w, topic)
                else:
                    callback = self._input_callback(spec, slots, counter, w, topic)
                self._subscribe(msg_type, topic, callback)

        if plan.sensors is not None:
            self.sensors = SensorPublishers(
                node, qos, self.memory, plan.sensors, self.lo, self.hi, self.namespaces, all_topics=plan.all_topics
            )
        for row, ns in enumerate(self.namespaces):
            node.create_service(Trigger, f"/{ns}/reset", self._reset_service([self.lo + row], f"/{ns}"))
        if self.index == 0:
            node.create_service(Trigger, "/batchsim/reset", self._reset_service(None, "all worlds"))
            node.create_service(SetBool, "/batchsim/pause", self._pause_service)
            node.create_service(Trigger, "/batchsim/step", self._step_service)

    def start(self) -> None:
        """Spin the executor on its own thread."""
        self.executor = EventsExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._running = True
        self._thread = threading.Thread(target=self._spin, name=f"ros_bridge_{self.index}", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop spinning and leave the ROS graph. Safe to call twice."""
        running, self._running = self._running, False
        if running and self._thread is not None:
            self._thread.join(timeout=2.0)
        try:
            self.node.destroy_node()
        except Exception:
            pass
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
        self._beat[self.index] += 1
        snap = self._read_snapshot()
        if snap is not None:
            self._publish(snap)
        if self.sensors is not None:
            self.sensors.publish()
        done = int(self._svc_done[self.index])
        if done != self._last_done:
            self._last_done = done
            with self._service_cond:
                self._service_cond.notify_all()
        now = wallclock.monotonic()
        due = self._due
        if now >= due["refresh"]:
            due["refresh"] = now + SUBSCRIBER_REFRESH
            self._refresh()
        if now >= due["scan"]:
            due["scan"] = now + GRAPH_SCAN
            self._scan_graph()
        if now >= due["diag"] and self.snapshot.n >= 0:
            due["diag"] = now + DIAGNOSTICS_PERIOD
            self._publish_diagnostics()
            self.throttle.flush()

    def _read_snapshot(self) -> Snapshot | None:
        """This worker's rows of the newest snapshot, if newer than the last; None otherwise."""
        m = self.memory
        latest, seq = m["latest"], m["seq"]
        lo, hi = self.lo, self.hi
        snap = self.snapshot
        for _ in range(8):
            n = int(latest[0])
            if n <= snap.n:
                return None
            b = n % 2
            if int(seq[b]) != 2 * n + 2:
                continue  # being rewritten: a newer one is coming
            meta = m["meta"][b].copy()
            status = m["status"][b, lo:hi].copy()
            flags = m["flags"][b, lo:hi].copy()
            written = m["written"][b].copy()
            channels = {
                c: m[f"ch{c}"][b, lo:hi].copy() for c in range(len(self.plan.channels)) if written[c] == n
            }
            if int(seq[b]) != 2 * n + 2:
                continue  # torn: the loop lapped us
            snap.n, snap.period, snap.time, snap.forced = n, int(meta[1]), float(meta[2]), bool(meta[3])
            snap.status, snap.flags, snap.written, snap.channels = status, flags, written, channels
            return snap
        return None

    def _publish(self, snap: Snapshot) -> None:
        sec, nanosec = stamp_of(snap.time)
        # /clock only while someone listens (re-read with the other counts; a new subscriber
        # gets the time at once): a publish costs ~30 us, a period at 1 kHz has 1000
        if self._clock_subscribers and ((sec, nanosec) != self._last_clock or snap.forced):
            self._last_clock = (sec, nanosec)
            self._clock_pub.publish(clock_payload(sec, nanosec))
        for out in self._active:
            if snap.forced or snap.period % out.spec.every == 0:
                self._publish_rows(out, snap, out.rows, sec, nanosec)

    def _publish_rows(self, out: _Output, snap: Snapshot, rows: list[int], sec: int, nanosec: int) -> None:
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

    def _refresh(self) -> None:
        """Lazy publishing: which rows have subscribers; which channels this worker needs.
        A world's first subscriber gets the newest state at once, so a node that waits for
        the state before it commands (lockstep) is not left waiting for the next period."""
        snap = self.snapshot
        sec, nanosec = stamp_of(snap.time)
        demand = np.zeros(len(self.plan.channels), dtype=np.uint8)
        active = []
        for out in self._outputs:
            before = set(out.rows)
            out.rows = [r for r, p in enumerate(out.publishers) if p is not None and p.get_subscription_count() > 0]
            if out.rows:
                active.append(out)
                for c in out.spec.channels:
                    demand[c] = 1
                new = [r for r in out.rows if r not in before]
                if new and snap.n >= 0:
                    self._publish_rows(out, snap, new, sec, nanosec)
        self._active = active
        if self.sensors is not None:
            self.sensors.refresh()
        if len(demand):
            self.memory["demand"][self.index, : len(demand)] = demand
        if self._clock_pub is not None:
            count = self._clock_pub.get_subscription_count()
            if count > self._clock_subscribers and snap.n >= 0:
                self._clock_pub.publish(clock_payload(sec, nanosec))
            self._clock_subscribers = count

    def _scan_graph(self) -> None:
        """Create on-request publishers and actuator subscriptions someone asks for; reject
        commands to actuators this model does not have."""
        node = self.node
        for name, _types in node.get_topic_names_and_types():
            if self.sensors is not None and self.sensors.requested(name):
                self._due["refresh"] = 0.0
                continue
            hit = self._on_request.get(name)
            if hit is not None:
                if node.count_subscribers(name) > 0:
                    out, row = hit
                    out.publishers[row] = node.create_publisher(out.msg_type, name, self.qos)
                    del self._on_request[name]
                    self._due["refresh"] = 0.0
                continue
            act = self._actuators.get(name)
            if act is not None:
                w, c = act
                if c >= 0 and node.count_publishers(name) > 0:
                    callback = self._single_callback(w, c, name, self.plan.interfaces, self.plan.owners)
                    self._subscribe(Float64, name, callback)
                    self._actuators[name] = (w, -1)  # subscribed
                continue
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

    def _publish_diagnostics(self) -> None:
        if self._diag_pub.get_subscription_count() == 0:
            return
        snap = self.snapshot
        out = DiagnosticArray()
        sec, nanosec = stamp_of(snap.time)
        out.header.stamp.sec, out.header.stamp.nanosec = sec, nanosec
        mine, host = self.rejections, self.host_rejections
        # what the controllers refused in the loop since the last round, on its last topic
        host_counts = host.count[self.lo : self.hi].copy()
        for row in np.flatnonzero(host_counts != self._host_seen).tolist():
            topic = host.reason(self.lo + row).partition(": ")[0]
            self._count_rejection(row, topic, Problem.INVALID, int(host_counts[row] - self._host_seen[row]))
        self._host_seen = host_counts
        with self._rejected_lock:
            rejected = [sorted(c.items()) for c in self._rejected]
        for row, ns in enumerate(self.namespaces):
            w = self.lo + row
            bits = int(snap.status[row])
            flags = int(snap.flags[row])
            problems = [s.name.lower() for s in Status if s and bits & s]
            if flags & FLAG_TIMED_OUT:
                problems.append("command_timeout")
            level = DiagnosticStatus.OK
            if bits & (Status.DIVERGED | Status.OVERFLOW):
                level = DiagnosticStatus.ERROR
            elif problems:
                level = DiagnosticStatus.WARN
            count = int(mine.count[w]) + int(host.count[w])
            last = ""
            if count:
                last = host.reason(w) if host.period[w] > mine.period[w] else mine.reason(w)
            message = "ok" if not problems else ", ".join(problems)
            if flags & FLAG_FROZEN:
                message += " (frozen until reset: its state topics stopped)"
            if flags & FLAG_BAD and last:
                message += f" ({last})"
            out.status.append(
                DiagnosticStatus(
                    level=level,
                    name=f"batchsim: {ns}",
                    message=message,
                    hardware_id=ns,
                    values=[
                        KeyValue(key="status", value=str(bits)),
                        KeyValue(key="frozen", value=str(bool(flags & FLAG_FROZEN)).lower()),
                        KeyValue(key="bad_commands", value=str(count)),
                        KeyValue(key="command_timeout", value=str(bool(flags & FLAG_TIMED_OUT)).lower()),
                        KeyValue(key="last_problem", value=last),
                    ]
                    + [KeyValue(key=f"rejected {topic} {reason}", value=str(n)) for (topic, reason), n in rejected[row]],
                )
            )
        self._diag_pub.publish(out)

    # --- the executor thread ---
    def _spin(self) -> None:
        while self._running:
            try:
                self.executor.spin_once(timeout_sec=FLUSH_AFTER if self._pending else 0.1)
            except (ExternalShutdownException, ShutdownException):
                break
            except Exception as e:  # a failing callback must not end the worker
                if not self._running or not self.context.ok():
                    break
                self.throttle.warn(("callback", type(e).__name__), f"ROS callback failed: {type(e).__name__}: {e}")
            if self._pending and wallclock.monotonic() - self._pending_since >= FLUSH_AFTER:
                self._flush()

    def _subscribe(self, msg_type: type, topic: str, callback: Callable[[Any], None]) -> None:
        self._subscriptions.append(self.node.create_subscription(msg_type, topic, callback, self.qos))

    def _nudge(self) -> None:
        """Lockstep: tell the loop a command arrived."""
        if self.notify_fd is not None:
            try:
                os.write(self.notify_fd, b"c")
            except (BlockingIOError, OSError):
                pass  # the pipe is full: the loop has been told already

    def _reject(self, world: int, topic: str, problem: Problem, reason: str) -> None:
        self.rejections.put(world, self.snapshot.period, f"{topic}: {reason}")
        self._count_rejection(world - self.lo, topic, problem, 1)
        self.throttle.warn((topic, problem), f"rejected command on {topic}: {reason}")

    def _count_rejection(self, row: int, topic: str, problem: Problem, count: int) -> None:
        with self._rejected_lock:
            counts = self._rejected[row]
            counts[topic, problem.value] = counts.get((topic, problem.value), 0) + count

    def _vector_callback(self, w: int, topic: str, interfaces: list[str], owners: list[str]) -> Callable[[Any], None]:
        def callback(msg: Float64MultiArray) -> None:
            row = np.frombuffer(msg.data, dtype=np.float64) if len(msg.data) else np.zeros(0)
            problem = check_vector(row, interfaces, owners)
            if problem is not None:
                self._reject(w, topic, *problem)
                return
            self.commands.put_row(w, row)
            self._nudge()

        return callback

    def _single_callback(self, w: int, c: int, topic: str, interfaces: list[str], owners: list[str]) -> Callable[[Any], None]:
        def callback(msg: Float64) -> None:
            problem = check_single(msg.data, c, interfaces, owners)
            if problem is not None:
                self._reject(w, topic, *problem)
                return
            self.commands.put(w, c, msg.data)
            self._nudge()

        return callback

    def _input_callback(self, spec: Any, slots: SlotWriter, counter: np.ndarray, w: int, topic: str) -> Callable[[Any], None]:
        def callback(msg: Any) -> None:
            try:
                row = parse_row(spec, msg)
            except (ValueError, TypeError) as e:
                self._reject(w, topic, Problem.MALFORMED, str(e))
                return
            slots.put_row(w, row)
            self._nudge()

        return callback

    def _trajectory_callback(self, i: int, w: int, topic: str) -> Callable[[Any], None]:
        spec = self.plan.inputs[i]

        def callback(msg: Any) -> None:
            try:
                parsed = parse_trajectory(msg)
            except (ValueError, TypeError) as e:
                self._reject(w, topic, Problem.MALFORMED, str(e))
                return
            if spec.max_points and len(parsed[1]) > spec.max_points:
                self._reject(w, topic, Problem.MALFORMED, f"{len(parsed[1])} points, more than {spec.max_points}")
                return
            with self._pending_lock:
                if not self._pending:
                    self._pending_since = wallclock.monotonic()
                self._pending.setdefault(i, []).append((w, *parsed))

        return callback

    def _flush(self) -> None:
        """Hand every trajectory that arrived to the loop: one ring record per input."""
        with self._pending_lock:
            pending, self._pending = self._pending, {}
        for i, messages in pending.items():
            spec = self.plan.inputs[i]
            batch, kept, rejected = trajectory_batch(spec.joints, messages)
            for k, reason in rejected:
                w = messages[k][0]
                self._reject(w, f"/{self.plan.namespaces[w]}/{spec.topic}", Problem.MALFORMED, reason)
            if not len(batch):
                continue
            with self._ring_lock:
                ok = self.ring.put(Kind.TRAJECTORY, encode_trajectories(i, batch))
            if not ok:
                for w in batch.worlds.tolist():
                    self._reject(
                        w, f"/{self.plan.namespaces[w]}/{spec.topic}", Problem.BACKLOG, "the loop is too far behind to take it"
                    )
                continue
            np.add.at(self.memory[f"{spec.slots}.seq"], batch.worlds, 1)
        self._nudge()

    # --- services (executor thread; each waits for the loop) ---
    def _request(self, kind: Kind, encode: Callable[[int], bytes]) -> int | None:
        issued = self.memory["svc.issued"]
        with self._ring_lock:
            ticket = int(issued[self.index]) + 1
            if not self.ring.put(kind, encode(ticket)):
                return None
            issued[self.index] = ticket
        self._nudge()
        return ticket

    def _wait(self, ticket: int | None) -> bool:
        if ticket is None:
            return False
        done = self.memory["svc.done"]
        deadline = wallclock.monotonic() + SERVICE_WAIT
        with self._service_cond:
            while int(done[self.index]) < ticket:
                left = deadline - wallclock.monotonic()
                if left <= 0 or not self._running:
                    return False
                self._service_cond.wait(min(left, 0.05))
        return True

    def _reset_service(self, worlds: list[int] | None, target: str) -> Callable[[Any, Any], Any]:
        def reset(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
            done = self._wait(self._request(Kind.RESET, lambda t: encode_reset(t, worlds)))
            response.success = True
            response.message = f"reset {target}" if done else f"reset of {target} queued (the loop is busy)"
            return response

        return reset

    def _pause_service(self, request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        done = self._wait(self._request(Kind.PAUSE, lambda t: encode_ticket(t, int(bool(request.data)))))
        response.success = done
        response.message = ("paused" if request.data else "running") if done else "the loop did not answer in time"
        return response

    def _step_service(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        done = self._wait(self._request(Kind.STEP, lambda t: encode_ticket(t)))
        ok = done and bool(self.memory["svc.ok"][self.index])
        response.success = ok
        if not done:
            response.message = "the loop did not step in time"
        elif not ok:
            response.message = "not paused: /batchsim/step advances one control period while paused"
        else:
            response.message = f"stepped to sim time {float(self.memory['svc.time'][self.index]):.6f} s"
        return response


def _full(namespace: str, name: str) -> str:
    return f"{namespace.rstrip('/')}/{name}"


def _die_with_parent() -> None:
    """SIGTERM when the physics process dies, however it dies (Linux)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    index, wake_fd, status_fd, notify_fd = (int(a) for a in argv[:4])
    check = "--check" in argv
    parent = os.getppid()
    _die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the physics process, which stops us

    def on_term(signum: int, frame: Any) -> None:
        raise SystemExit(0)

    signal.signal(signal.SIGTERM, on_term)
    if os.getppid() != parent:
        return 0
    status = os.fdopen(status_fd, "w", buffering=1)
    try:
        plan: FleetPlan = pickle.load(sys.stdin.buffer)
    except (EOFError, pickle.UnpicklingError):
        return 0  # the physics process stopped (Ctrl-C) before it handed the whole plan over
    memory: Memory | None = None
    worker = None
    ready = False
    try:
        memory = Memory.attach(plan.layout, plan.memory_name)
        os.set_blocking(notify_fd, False)
        worker = Worker(plan, index, memory, notify_fd=notify_fd if plan.lockstep else None)
        conflict = worker.check_conflicts() if check else None
        if conflict is not None:
            status.write(f"conflict {conflict[0]} {conflict[1]}\n")
            return 0
        worker.build()
        worker.start()
        status.write("ready\n")
        ready = True
        worker.serve(wake_fd)
        return 0
    except SystemExit:
        return 0
    except BaseException as e:
        if os.getppid() != parent:
            return 0  # the physics process went (and took the shared memory): nothing to say
        if not ready:
            try:
                status.write(f"error {type(e).__name__}: {e}\n")
            except OSError:
                pass
        raise
    finally:
        if worker is not None:
            worker.close()
        if memory is not None:
            memory.close()


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)  # all is closed: skip the interpreter's teardown of rclpy and DDS (tenths of a second)
