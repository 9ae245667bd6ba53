"""The ROS 2 bridge: one rclpy node for the whole fleet, every world on its own namespace.

`start_bridge(sim, loop, args)` makes a `Bridge`, which is a loop participant: its
`update()` runs in the loop thread, between `read()` and `write()`, once per control
period. ROS callbacks run on the bridge's executor thread and only stash what they
receive (`CommandInbox`) or set flags; the simulation is touched from the loop thread
only, and publishing happens there too, so a published message is exactly the state of
the period it is stamped with.

Per world, under its namespace `<ns>` (`world_3` from the template `world_{i}`):

    <ns>/joint_states                  sensor_msgs/JointState        (publish rate)
    <ns>/sensors/<sensor>              std_msgs/Float64 or Float64MultiArray (sensor rate)
    <ns>/sensors/<site>/imu            sensor_msgs/Imu        gyro + accelerometer (+ framequat) on one site
    <ns>/sensors/<site>/wrench         geometry_msgs/WrenchStamped   force + torque on one site
    <ns>/odom                          nav_msgs/Odometry      the floating base (spec.floating_base)
    <ns>/actuators/<actuator>/command  std_msgs/Float64 (subscribed)
    <ns>/commands                      std_msgs/Float64MultiArray (subscribed), one value per
                                       command interface in `batchsim info` order
    <ns>/reset                         std_srvs/Trigger: reset this world only

and once per process: `/clock` (every control period), `/diagnostics` (per-world status,
about twice a second), `/batchsim/reset` (Trigger), `/batchsim/pause` (SetBool),
`/batchsim/step` (Trigger; one control period while paused).

Topics nobody subscribes to are not filled or published (subscriber counts are
refreshed twice a second), so a fleet pays only for what is listened to.
"""

from __future__ import annotations

import argparse
import array
import atexit
import math
import re
import threading
import time as wallclock
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import WrenchStamped
from nav_msgs.msg import Odometry
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64, Float64MultiArray
from std_srvs.srv import SetBool, Trigger

from batchsim.hardware import BatchedSystem, Status
from batchsim.loop import Participant, SimLoop
from batchsim.model import InterfaceKind
from ros_bridge.inbox import CommandInbox, Rejection
from ros_bridge.naming import DEFAULT_TEMPLATE, ros_names, world_namespaces

LOG_INTERVAL = 2.0  # s of wall time between two log lines of one kind (topic and problem)
SUBSCRIBER_REFRESH = 0.5  # s: how often subscriber counts are re-read (lazy publishing)
GRAPH_SCAN = 2.0  # s: how often the graph is scanned for commands to unknown actuators
DIAGNOSTICS_PERIOD = 0.5  # s of wall time
SERVICE_WAIT = 2.0  # s a reset or step service waits for the loop to carry it out
_BAD = np.uint8(Status.BAD_COMMAND)
_ACTUATOR_TOPIC = re.compile(r"^/(.+)/actuators/([^/]+)/command$")


def start_bridge(sim: BatchedSystem, loop: SimLoop, args: argparse.Namespace, **overrides: Any) -> Bridge:
    """The bridge for a `batchsim` run, from its command-line flags; already spinning.

    The bridge is put first among the loop's participants (so controllers after it see
    this period's commands), and, with --lockstep, becomes the loop's gate.
    """
    options = dict(
        namespace=getattr(args, "namespace", DEFAULT_TEMPLATE),
        publish_rate=getattr(args, "publish_rate", None),
        sensor_rate=getattr(args, "sensor_rate", None),
        qos_depth=getattr(args, "qos_depth", None),
        reliability=getattr(args, "reliability", None),
        command_timeout=getattr(args, "command_timeout", None),
        lockstep=getattr(args, "lockstep", False),
        lockstep_timeout=getattr(args, "lockstep_timeout", 1.0),
    )
    options.update(overrides)
    bridge = Bridge(sim, loop, **options)
    # rclpy aborts the process if a context is still up at exit: close even if the run fails
    atexit.register(bridge.close)
    bridge.attach()
    return bridge


class Bridge:
    """One rclpy node serving every world of `sim`. A loop `Participant`.

    For controllers (ros_bridge/controllers.py) to build on:
      node: the rclpy node; create publishers and subscriptions on it (callbacks run on
        the bridge's executor thread: stash, never touch `sim` there).
      namespaces: one namespace per world, no leading `/` (`"world_3"`).
      qos: the QoSProfile from --qos-depth / --reliability (or the MJCF's plugin keys).
      stamp(time): builtin_interfaces/Time for a sim time.
      add_participant(p): run `p.update(sim, time, period)` in the loop thread after the
        bridge, every control period.
      claim(controller, interfaces) / release(controller): reserve command interfaces;
        raw topic commands to them are then rejected, naming the controller.
      publish_joint_states: False when a joint state broadcaster publishes them instead.
      on_reset: callables `f(worlds)` run in the loop thread after worlds were reset
        through a service (`worlds` is None for all).

    Args:
      sim: the system, configured.
      loop: the loop that will run it.
      namespace: the per-world namespace template, with `{i}`.
      publish_rate: Hz for joint_states and typed messages; None: every control period.
      sensor_rate: Hz for sensors/<sensor> topics; None: the publish rate.
      qos_depth, reliability: QoS of topics ("reliable" or "best_effort"); None: the MJCF's
        mujoco.ros2 keys, else 10 and reliable.
      command_timeout: sim seconds without a command after which a world that had been
        commanded goes safe (position interfaces hold the measured position, velocity
        and effort go to 0); None: hold the last command forever.
      lockstep: each control period waits until every world's command has arrived.
      lockstep_timeout: wall seconds a lockstep period waits before it goes on.
      publish_joint_states: publish <ns>/joint_states (off when a controller does).
    """

    def __init__(
        self,
        sim: BatchedSystem,
        loop: SimLoop,
        *,
        namespace: str = DEFAULT_TEMPLATE,
        publish_rate: float | None = None,
        sensor_rate: float | None = None,
        qos_depth: int | None = None,
        reliability: str | None = None,
        command_timeout: float | None = None,
        lockstep: bool = False,
        lockstep_timeout: float = 1.0,
        publish_joint_states: bool = True,
        node_name: str = "batchsim",
    ):
        spec = sim.spec
        self.sim = sim
        self.loop = loop
        self.nworld = nworld = sim.nworld
        self.namespaces = world_namespaces(nworld, namespace, spec.ros.ros_namespace if spec.ros else None)
        self.publish_every = self._decimation(publish_rate, loop.control_rate, "--publish-rate")
        self.sensor_every = (
            self.publish_every
            if sensor_rate is None
            else self._decimation(sensor_rate, loop.control_rate, "--sensor-rate")
        )
        if command_timeout is not None and command_timeout <= 0:
            raise ValueError(f"--command-timeout must be > 0 seconds, got {command_timeout}")
        if lockstep_timeout <= 0:
            raise ValueError(f"--lockstep-timeout must be > 0 seconds, got {lockstep_timeout}")
        self.command_timeout = command_timeout
        self.lockstep = lockstep
        self.lockstep_timeout = lockstep_timeout

        plugin = spec.ros
        depth = qos_depth if qos_depth is not None else (plugin.topic_queue_size if plugin else 10)
        if depth < 1:
            raise ValueError(f"--qos-depth must be >= 1, got {depth}")
        rel = reliability or (plugin.topic_reliability if plugin else "reliable")
        self.qos = QoSProfile(
            depth=depth,
            history=HistoryPolicy.KEEP_LAST,
            reliability=ReliabilityPolicy.BEST_EFFORT if rel == "best_effort" else ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.VOLATILE,
        )

        self.inbox = CommandInbox(nworld, spec.command_interfaces)
        self.on_reset: list[Callable[[np.ndarray | None], None]] = []
        self._participants: list[Participant] = []
        self._lock = threading.Lock()
        self._resets: set[int] | None = set()  # None: reset all
        self._reset_requested = 0
        self._reset_done = 0
        self._reset_cond = threading.Condition(self._lock)
        self._step_event: threading.Event | None = None
        self._period = 0
        self._log_last: dict[str, list[float]] = {}
        self._gate_since: float | None = None

        # per-world command bookkeeping (loop thread)
        self._bad = np.zeros(nworld, dtype=bool)
        self._bad_count = np.zeros(nworld, dtype=np.int64)
        self._last_problem = [""] * nworld
        self._last_command = np.full(nworld, np.inf)  # sim time of the last command; inf: never
        self._timed_out = np.zeros(nworld, dtype=bool)
        self._safe = self._safe_plan()
        self._diag_due = 0.0
        self._diag_dirty = False

        self.context = Context()
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        try:
            self.node = Node(node_name, context=self.context)
            self._build(publish_joint_states)
        except BaseException:
            rclpy.try_shutdown(context=self.context)
            raise
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._running = True
        self._thread = threading.Thread(target=self._spin, name="ros_bridge", daemon=True)
        self._thread.start()

    # --- public helpers ---
    @staticmethod
    def stamp(time: float) -> Time:
        """builtin_interfaces/Time for a sim time in seconds."""
        sec = math.floor(time)
        nanosec = int(round((time - sec) * 1e9))
        if nanosec >= 1_000_000_000:
            sec, nanosec = sec + 1, nanosec - 1_000_000_000
        return Time(sec=int(sec), nanosec=nanosec)

    def attach(self) -> None:
        """Join the loop: first participant, and its gate with lockstep."""
        self.loop.participants.insert(0, self)
        if self.lockstep:
            self.loop.gate = self.gate

    def add_participant(self, participant: Participant) -> None:
        """Run `participant.update(sim, time, period)` every period, right after the bridge."""
        self._participants.append(participant)

    def claim(self, controller: str, interfaces: Sequence[str]) -> None:
        """Reserve command interfaces for a controller; ValueError if unknown or taken."""
        self.inbox.claim(controller, interfaces)

    def release(self, controller: str) -> None:
        self.inbox.release(controller)

    @property
    def publish_joint_states(self) -> bool:
        return bool(self._js)

    @publish_joint_states.setter
    def publish_joint_states(self, value: bool) -> None:
        if not value and self._js:
            entries, self._js, self._js_active = self._js, [], []
            for e in entries:
                self.node.destroy_publisher(e[0])
        elif value and not self._js:
            self._build_joint_states()

    def describe(self) -> str:
        ns = self.namespaces
        where = f"/{ns[0]}" if len(ns) == 1 else f"/{ns[0]} .. /{ns[-1]}"
        rate = self.loop.control_rate / self.publish_every
        mode = ", lockstep" if self.lockstep else ""
        rel = "best_effort" if self.qos.reliability == ReliabilityPolicy.BEST_EFFORT else "reliable"
        return f"{where} (publish {rate:g} Hz, QoS {rel} depth {self.qos.depth}{mode})"

    def close(self) -> None:
        """Stop spinning and leave the ROS graph. Safe to call twice."""
        if not self._running:
            return
        self._running = False
        self.loop.gate = None if self.loop.gate == self.gate else self.loop.gate
        try:
            self.executor.shutdown(timeout_sec=1.0)
        except Exception:
            pass
        self._thread.join(timeout=2.0)
        try:
            self.node.destroy_node()
        finally:
            rclpy.try_shutdown(context=self.context)

    # --- the loop thread ---
    def update(self, sim: BatchedSystem, time: float, period: float) -> None:
        """Every control period: resets, incoming commands, timeouts, then publishing."""
        self._apply_resets()
        worlds, rejections = self.inbox.take(sim.command)
        if worlds is not None:
            self._last_command[worlds] = time
            self._timed_out[worlds] = False
            if self._bad.any():
                self._bad[worlds] = False
                self._diag_dirty = True
        if rejections:
            self._rejected(rejections)
        if self.command_timeout is not None:
            self._check_timeouts(sim, time)

        if self.lockstep:  # the gate published this period's state before waiting for commands
            stamp = self._clock_msg.clock
        else:
            stamp = self._publish_period(sim, time)
        now = wallclock.perf_counter()
        if now >= self._diag_due or (self._diag_dirty and now >= self._diag_due - DIAGNOSTICS_PERIOD + 0.1):
            self._publish_diagnostics(sim, stamp)
            self._diag_due = now + DIAGNOSTICS_PERIOD

        for p in self._participants:
            p.update(sim, time, period)

        event = self._step_event
        if event is not None:
            self._step_event = None
            event.set()

    def _publish_period(self, sim: BatchedSystem, time: float) -> Time:
        """/clock every period; state and sensors at their rates. Returns the stamp."""
        k = self._period
        self._period = k + 1
        stamp = self.stamp(time)
        self._clock_msg.clock = stamp
        self._clock_pub.publish(self._clock_msg)
        if k % self.publish_every == 0:
            self._publish_state(sim, stamp)
        if k % self.sensor_every == 0 and self._sensor_active:
            self._publish_sensors(sim)
        return stamp

    def after_write(self, sim: BatchedSystem, time: float, period: float) -> None:
        """write() clears BAD_COMMAND for rows it applied; keep it on worlds whose last
        command the bridge rejected."""
        if self._bad.any():
            sim.status[self._bad] |= _BAD

    def idle(self, sim: BatchedSystem, time: float) -> None:
        """While paused: carry out resets (and show them), keep diagnostics alive."""
        self._gate_since = None
        if self._apply_resets():
            stamp = self.stamp(time)
            self._publish_state(sim, stamp)
        now = wallclock.perf_counter()
        if now >= self._diag_due:
            self._publish_diagnostics(sim, self.stamp(time))
            self._diag_due = now + DIAGNOSTICS_PERIOD

    def gate(self, sim_time: float) -> bool:
        """Lockstep: True when every world's command for this period has arrived, or the
        wait timed out; False to be asked again (so stop() and pause() stay responsive)."""
        self._apply_resets()
        now = wallclock.perf_counter()
        if self._gate_since is None:
            # show the state this period starts from, so commands can be computed from it
            self._gate_since = now
            self.sim.read(sim_time, self.loop.period)
            self._publish_period(self.sim, sim_time)
        left = self._gate_since + self.lockstep_timeout - now
        ready = self.inbox.wait_ready(min(max(left, 0.0), 0.05))
        if ready.all():
            self._gate_since = None
            return True
        if wallclock.perf_counter() - self._gate_since < self.lockstep_timeout:
            return False
        self._gate_since = None
        missing = [self.namespaces[w] for w in np.flatnonzero(~ready)[:8]]
        self._warn(
            "lockstep",
            f"lockstep: no command within {self.lockstep_timeout:g} s from {', '.join(missing)}"
            + (" ..." if (~ready).sum() > 8 else "")
            + f" at sim time {sim_time:.3f} s; going on with their last command",
        )
        return True

    def _apply_resets(self) -> bool:
        if not self._reset_requested > self._reset_done:
            return False
        with self._lock:
            resets, requested = self._resets, self._reset_requested
            self._resets = set()
        rows = None if resets is None else np.array(sorted(resets), dtype=np.int64)
        self.sim.reset(worlds=rows)
        sel = slice(None) if rows is None else rows
        self._last_command[sel] = np.inf
        self._timed_out[sel] = False
        self._bad[sel] = False
        self._diag_dirty = True
        for hook in self.on_reset:
            hook(rows)
        with self._lock:
            self._reset_done = requested
            self._reset_cond.notify_all()
        return True

    def _rejected(self, rejections: list[Rejection]) -> None:
        for r in rejections:
            self._bad[r.world] = True
            self._bad_count[r.world] += 1
            self._last_problem[r.world] = f"{r.topic}: {r.problem}"
            kind = "claimed" if r.controller else r.problem.split(" ", 1)[0]
            self._warn(f"{r.topic}|{kind}", f"rejected command on {r.topic}: {r.problem}")
        self._diag_dirty = True

    def _check_timeouts(self, sim: BatchedSystem, time: float) -> None:
        stale = (time - self._last_command > self.command_timeout + 1e-9) & ~self._timed_out
        if not stale.any():
            return
        rows = np.flatnonzero(stale)
        self._timed_out[rows] = True
        hold_cols, hold_src, zero_cols = self._safe
        free = self.inbox.free
        command = sim.command
        for c, s in zip(hold_cols, hold_src, strict=True):
            if free[c]:
                command[rows, c] = sim.state[rows, s]
        for c in zero_cols:
            if free[c]:
                command[rows, c] = 0.0
        names = ", ".join(self.namespaces[w] for w in rows[:8]) + (" ..." if len(rows) > 8 else "")
        self._warn(
            "timeout",
            f"{names}: no command for {self.command_timeout:g} s (--command-timeout); "
            "holding position, zero velocity and effort",
        )
        self._diag_dirty = True

    def _safe_plan(self) -> tuple[list[int], list[int], list[int]]:
        """Where each command goes on a command timeout: position interfaces to the
        measured joint position (state column), velocity and effort to zero."""
        spec = self.sim.spec
        column = {name: i for i, name in enumerate(spec.state_interfaces)}
        hold_cols, hold_src, zero_cols = [], [], []
        for c, cmd in enumerate(spec.commands):
            if cmd.kind is InterfaceKind.POSITION:
                src = column.get(f"{cmd.joint}/position") if cmd.joint else None
                if src is not None:  # a position actuator without a measured joint holds its command
                    hold_cols.append(c)
                    hold_src.append(src)
            else:
                zero_cols.append(c)
        return hold_cols, hold_src, zero_cols

    def _warn(self, key: str, text: str) -> None:
        """A log line at most every LOG_INTERVAL s per key, counting the ones held back."""
        now = wallclock.perf_counter()
        last = self._log_last.get(key)
        if last is not None and now - last[0] < LOG_INTERVAL:
            last[1] += 1
            return
        held = int(last[1]) if last is not None else 0
        self._log_last[key] = [now, 0]
        self.node.get_logger().warning(text + (f" ({held} more like it in the last {LOG_INTERVAL:g} s)" if held else ""))

    # --- building the graph ---
    @staticmethod
    def _decimation(rate: float | None, control_rate: float, flag: str) -> int:
        if rate is None:
            return 1
        if rate <= 0:
            raise ValueError(f"{flag} must be > 0 Hz, got {rate:g}")
        every = max(1, round(control_rate / rate))
        if abs(control_rate / every - rate) > 1e-6 * rate:
            raise ValueError(
                f"{flag} {rate:g} Hz must divide the control rate {control_rate:g} Hz "
                f"(try {control_rate / every:g} Hz)"
            )
        return every

    def _build(self, publish_joint_states: bool) -> None:
        node, spec, qos = self.node, self.sim.spec, self.qos
        self._clock_pub = node.create_publisher(Clock, "/clock", QoSProfile(depth=1))
        self._clock_msg = Clock()
        self._diag_pub = node.create_publisher(DiagnosticArray, "/diagnostics", QoSProfile(depth=10))

        # joint_states: (state columns per kind, -1 where a joint lacks the kind)
        column = {name: i for i, name in enumerate(spec.state_interfaces)}
        self._joint_names = [j.name for j in spec.joints]
        self._js_cols: list[np.ndarray | None] = []
        for kind in ("position", "velocity", "effort"):
            cols = np.array([column.get(f"{j}/{kind}", -1) for j in self._joint_names], dtype=np.intp)
            self._js_cols.append(None if (cols < 0).all() else cols)
        self._js: list[tuple[Any, ...]] = []
        self._js_active: list[tuple[Any, ...]] = []
        if publish_joint_states and self._joint_names:
            self._build_joint_states()

        # sensors/<sensor>: (publisher, message, data view or None, sensor name, world)
        sensor_topics = ros_names([s.name for s in spec.sensors])
        self._sensors: list[tuple[Any, ...]] = []
        self._sensor_active: list[tuple[Any, ...]] = []
        for w, ns in enumerate(self.namespaces):
            for s, topic in zip(spec.sensors, sensor_topics, strict=True):
                if s.dim == 1:
                    pub = node.create_publisher(Float64, f"/{ns}/sensors/{topic}", qos)
                    self._sensors.append((pub, Float64(), None, s.name, w))
                else:
                    msg = Float64MultiArray()
                    msg.data = array.array("d", bytes(8 * s.dim))
                    view = _view(msg.data)
                    pub = node.create_publisher(Float64MultiArray, f"/{ns}/sensors/{topic}", qos)
                    self._sensors.append((pub, msg, view, s.name, w))

        self._typed: list[_Typed] = []
        by_site: dict[str, dict[str, str]] = {}
        for s in spec.sensors:
            if s.objname and s.type in ("framequat", "gyro", "accelerometer", "force", "torque"):
                by_site.setdefault(s.objname, {}).setdefault(s.type, s.name)
        for site, kinds in by_site.items():
            site_topic = ros_names([site])[0]
            if "gyro" in kinds and "accelerometer" in kinds:
                self._typed.append(_ImuChannel(self, site, site_topic, kinds))
            if "force" in kinds and "torque" in kinds:
                self._typed.append(_WrenchChannel(self, site, site_topic, kinds))
        if spec.floating_base is not None:
            self._typed.append(_OdomChannel(self, spec.floating_base.body))

        # subscriptions: commands, actuators/<a>/command
        self._actuator_topics: list[set[str]] = []
        actuator_names = ros_names([c.actuator for c in spec.commands])
        self._command_subs = []
        for w, ns in enumerate(self.namespaces):
            topic = f"/{ns}/commands"
            self._command_subs.append(
                node.create_subscription(
                    Float64MultiArray, topic, _vector_callback(self.inbox, w, topic), qos
                )
            )
            known = set()
            for c, act in enumerate(actuator_names):
                topic = f"/{ns}/actuators/{act}/command"
                known.add(topic)
                self._command_subs.append(
                    node.create_subscription(Float64, topic, _single_callback(self.inbox, w, c, topic), qos)
                )
            self._actuator_topics.append(known)
        self._actuator_list = ", ".join(actuator_names) or "none"
        self._world_of = {ns: w for w, ns in enumerate(self.namespaces)}

        # services
        for w, ns in enumerate(self.namespaces):
            node.create_service(Trigger, f"/{ns}/reset", self._reset_service(w))
        node.create_service(Trigger, "/batchsim/reset", self._reset_service(None))
        node.create_service(SetBool, "/batchsim/pause", self._pause_service)
        node.create_service(Trigger, "/batchsim/step", self._step_service)

        node.create_timer(SUBSCRIBER_REFRESH, self._refresh_subscribers)
        node.create_timer(GRAPH_SCAN, self._scan_graph)

    def _build_joint_states(self) -> None:
        node, qos = self.node, self.qos
        entries = []
        for w, ns in enumerate(self.namespaces):
            msg = JointState()
            msg.name = list(self._joint_names)
            views = []
            for field, cols in zip(("position", "velocity", "effort"), self._js_cols, strict=True):
                if cols is None:
                    views.append(None)
                    continue
                setattr(msg, field, array.array("d", bytes(8 * len(cols))))
                views.append(_view(getattr(msg, field)))
            pub = node.create_publisher(JointState, f"/{ns}/joint_states", qos)
            entries.append((pub, msg, views[0], views[1], views[2], w))
        self._js = entries

    # --- publishing (loop thread) ---
    def _publish_state(self, sim: BatchedSystem, stamp: Time) -> None:
        active = self._js_active
        if active:
            state = sim.state
            gathered = []
            for cols in self._js_cols:
                if cols is None:
                    gathered.append(None)
                elif (cols >= 0).all():
                    gathered.append(state[:, cols])
                else:
                    g = state[:, np.maximum(cols, 0)]
                    g[:, cols < 0] = np.nan
                    gathered.append(g)
            pos, vel, eff = gathered
            for pub, msg, vp, vv, ve, w in active:
                msg.header.stamp = stamp
                if vp is not None:
                    vp[:] = pos[w]
                if vv is not None:
                    vv[:] = vel[w]
                if ve is not None:
                    ve[:] = eff[w]
                pub.publish(msg)
        for channel in self._typed:
            if channel.active:
                channel.publish(sim, stamp)

    def _publish_sensors(self, sim: BatchedSystem) -> None:
        data = sim.sensordata
        cache: dict[str, Any] = {}
        for pub, msg, view, name, w in self._sensor_active:
            values = cache.get(name)
            if values is None:
                values = cache[name] = data[name]
            if view is None:
                msg.data = float(values[w, 0])
            else:
                view[:] = values[w]
            pub.publish(msg)

    def _publish_diagnostics(self, sim: BatchedSystem, stamp: Time) -> None:
        self._diag_dirty = False
        if self._diag_pub.get_subscription_count() == 0:
            return
        out = DiagnosticArray()
        out.header.stamp = stamp
        status = sim.status
        for w, ns in enumerate(self.namespaces):
            bits = int(status[w]) | (int(Status.BAD_COMMAND) if self._bad[w] else 0)
            problems = [s.name.lower() for s in Status if s and bits & s]
            if self._timed_out[w]:
                problems.append("command_timeout")
            level = DiagnosticStatus.OK
            if bits & (Status.DIVERGED | Status.OVERFLOW):
                level = DiagnosticStatus.ERROR
            elif problems:
                level = DiagnosticStatus.WARN
            message = "ok" if not problems else ", ".join(problems)
            if self._bad[w] and self._last_problem[w]:
                message += f" ({self._last_problem[w]})"
            out.status.append(
                DiagnosticStatus(
                    level=level,
                    name=f"batchsim: {ns}",
                    message=message,
                    hardware_id=ns,
                    values=[
                        KeyValue(key="status", value=str(bits)),
                        KeyValue(key="bad_commands", value=str(int(self._bad_count[w]))),
                        KeyValue(key="command_timeout", value=str(bool(self._timed_out[w])).lower()),
                        KeyValue(key="last_problem", value=self._last_problem[w]),
                    ],
                )
            )
        self._diag_pub.publish(out)

    # --- the executor thread ---
    def _spin(self) -> None:
        while self._running:
            try:
                self.executor.spin_once(timeout_sec=0.1)
            except (ExternalShutdownException, rclpy.executors.ShutdownException):
                break
            except Exception as e:  # a failing callback must not end the bridge
                if not self._running or not self.context.ok():
                    break
                self._warn(f"callback|{type(e).__name__}", f"ROS callback failed: {type(e).__name__}: {e}")

    def _refresh_subscribers(self) -> None:
        """Lazy publishing: only topics with subscribers are filled and published."""
        self._js_active = [e for e in self._js if e[0].get_subscription_count() > 0]
        self._sensor_active = [e for e in self._sensors if e[0].get_subscription_count() > 0]
        for channel in self._typed:
            channel.refresh()

    def _scan_graph(self) -> None:
        """Commands published to actuator topics this model does not have: rejected, logged."""
        for name, _types in self.node.get_topic_names_and_types():
            match = _ACTUATOR_TOPIC.match(name)
            if match is None:
                continue
            w = self._world_of.get(match.group(1))
            if w is None or name in self._actuator_topics[w]:
                continue
            if self.node.count_publishers(name) > 0:
                self.inbox.reject(
                    w,
                    name,
                    f"no actuator named {match.group(2)!r} in this model (actuators: {self._actuator_list})",
                )

    def _reset_service(self, world: int | None) -> Callable[[Any, Any], Any]:
        target = "all worlds" if world is None else self.namespaces[world]

        def reset(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
            with self._lock:
                if world is None or self._resets is None:
                    self._resets = None
                else:
                    self._resets.add(world)
                self._reset_requested += 1
                ticket = self._reset_requested
            self.inbox.clear(None if world is None else np.array([world]))
            with self._lock:
                done = self._reset_cond.wait_for(lambda: self._reset_done >= ticket, SERVICE_WAIT)
            response.success = True
            response.message = f"reset {target}" if done else f"reset of {target} queued (the loop is busy)"
            return response

        return reset

    def _pause_service(self, request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        self.loop.pause(bool(request.data))
        response.success = True
        response.message = "paused" if request.data else "running"
        return response

    def _step_service(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if not self.loop.paused:
            response.success = False
            response.message = "not paused: /batchsim/step advances one control period while paused"
            return response
        event = threading.Event()
        self._step_event = event
        self.loop.single_step()
        done = event.wait(SERVICE_WAIT)
        response.success = done
        response.message = (
            f"stepped to sim time {self.loop.sim_time:.6f} s" if done else "the loop did not step in time"
        )
        return response


def _vector_callback(inbox: CommandInbox, world: int, topic: str) -> Callable[[Float64MultiArray], None]:
    def callback(msg: Float64MultiArray) -> None:
        inbox.put_vector(world, msg.data, topic)

    return callback


def _single_callback(inbox: CommandInbox, world: int, column: int, topic: str) -> Callable[[Float64], None]:
    def callback(msg: Float64) -> None:
        inbox.put_single(world, column, msg.data, topic)

    return callback


class _Typed:
    """A typed message per world (Imu, WrenchStamped, Odometry), published when listened to."""

    def __init__(self, bridge: Bridge, msg_type: type, topic: str):
        self.bridge = bridge
        self.pubs = [bridge.node.create_publisher(msg_type, f"/{ns}/{topic}", bridge.qos) for ns in bridge.namespaces]
        self.msgs = [msg_type() for _ in bridge.namespaces]
        self.wanted: list[int] = []
        self.active = False

    def refresh(self) -> None:
        self.wanted = [w for w, p in enumerate(self.pubs) if p.get_subscription_count() > 0]
        self.active = bool(self.wanted)

    def publish(self, sim: BatchedSystem, stamp: Time) -> None:
        raise NotImplementedError


class _ImuChannel(_Typed):
    """sensor_msgs/Imu from a gyro and an accelerometer (and a framequat) on one site."""

    def __init__(self, bridge: Bridge, site: str, site_topic: str, kinds: dict[str, str]):
        super().__init__(bridge, Imu, f"sensors/{site_topic}/imu")
        self.quat, self.gyro, self.accel = kinds.get("framequat"), kinds["gyro"], kinds["accelerometer"]
        for ns, msg in zip(bridge.namespaces, self.msgs, strict=True):
            msg.header.frame_id = f"{ns}/{site}"
            if self.quat is None:
                msg.orientation_covariance[0] = -1.0  # REP 145: no orientation estimate

    def publish(self, sim: BatchedSystem, stamp: Time) -> None:
        data = sim.sensordata
        gyro, accel = data[self.gyro].tolist(), data[self.accel].tolist()
        quat = data[self.quat].tolist() if self.quat else None
        for w in self.wanted:
            msg = self.msgs[w]
            msg.header.stamp = stamp
            if quat is not None:
                o, q = msg.orientation, quat[w]
                o.w, o.x, o.y, o.z = q  # MuJoCo quaternions are (w, x, y, z)
            v = msg.angular_velocity
            v.x, v.y, v.z = gyro[w]
            a = msg.linear_acceleration
            a.x, a.y, a.z = accel[w]
            self.pubs[w].publish(msg)


class _WrenchChannel(_Typed):
    """geometry_msgs/WrenchStamped from a force and a torque sensor on one site."""

    def __init__(self, bridge: Bridge, site: str, site_topic: str, kinds: dict[str, str]):
        super().__init__(bridge, WrenchStamped, f"sensors/{site_topic}/wrench")
        self.force, self.torque = kinds["force"], kinds["torque"]
        for ns, msg in zip(bridge.namespaces, self.msgs, strict=True):
            msg.header.frame_id = f"{ns}/{site}"

    def publish(self, sim: BatchedSystem, stamp: Time) -> None:
        force, torque = sim.sensordata[self.force].tolist(), sim.sensordata[self.torque].tolist()
        for w in self.wanted:
            msg = self.msgs[w]
            msg.header.stamp = stamp
            f, t = msg.wrench.force, msg.wrench.torque
            f.x, f.y, f.z = force[w]
            t.x, t.y, t.z = torque[w]
            self.pubs[w].publish(msg)


class _OdomChannel(_Typed):
    """nav_msgs/Odometry of the floating base: pose in <ns>/odom, twist in <ns>/<body>.

    MuJoCo's free joint has its linear velocity in the world frame and its angular
    velocity in the body frame; Odometry wants both in the child (body) frame.
    """

    def __init__(self, bridge: Bridge, body: str):
        super().__init__(bridge, Odometry, "odom")
        for ns, msg in zip(bridge.namespaces, self.msgs, strict=True):
            msg.header.frame_id = f"{ns}/odom"
            msg.child_frame_id = f"{ns}/{body}"

    def publish(self, sim: BatchedSystem, stamp: Time) -> None:
        base = sim.base_state  # pose, world-frame linear and body-frame angular velocity
        linear = _rotate_inverse(base[:, 3:7], base[:, 7:10])
        pose, lin, ang = base[:, :7].tolist(), linear.tolist(), base[:, 10:13].tolist()
        for w in self.wanted:
            msg = self.msgs[w]
            msg.header.stamp = stamp
            p, o = msg.pose.pose.position, msg.pose.pose.orientation
            p.x, p.y, p.z, o.w, o.x, o.y, o.z = pose[w]
            v, a = msg.twist.twist.linear, msg.twist.twist.angular
            v.x, v.y, v.z = lin[w]
            a.x, a.y, a.z = ang[w]
            self.pubs[w].publish(msg)


def _view(buffer: array.array) -> np.ndarray:
    """A NumPy view of a message's float64 array field, to fill it in place.

    Take it from the message after assigning (the setter may copy); the message then
    publishes whatever the view holds, with no allocation per message.
    """
    return np.frombuffer(buffer, dtype=np.float64)


def _rotate_inverse(quat: np.ndarray, vec: np.ndarray) -> np.ndarray:
    """Rotate (n, 3) world vectors into the frames of (n, 4) unit quaternions (w, x, y, z)."""
    w = quat[:, :1]
    u = -quat[:, 1:4]  # the conjugate rotates world -> body
    t = 2.0 * np.cross(u, vec)
    return vec + w * t + np.cross(u, t)
