"""The ROS topics of batchsim's controllers, under each world's namespace.

`bind_controllers(bridge, manager)` gives every controller in `manager` the topics its
`topics()` declares (batchsim/controllers/topics.py), for every world `<ns>`:

    joint_state_broadcaster     pub  <ns>/joint_states (use_local_topics: <ns>/<c>/joint_states)
                                     sensor_msgs/JointState; the bridge's own joint_states stop
    forward command flavours    sub  <ns>/<c>/commands              std_msgs/Float64MultiArray
    joint_trajectory_controller sub  <ns>/<c>/joint_trajectory      trajectory_msgs/JointTrajectory
                                pub  <ns>/<c>/controller_state/reference  sensor_msgs/JointState
                                pub  <ns>/<c>/controller_state/feedback   sensor_msgs/JointState
                                pub  <ns>/<c>/controller_state/error      sensor_msgs/JointState
    diff_drive_controller       sub  <ns>/<c>/cmd_vel  geometry_msgs/TwistStamped
                                     (use_stamped_vel: false -> geometry_msgs/Twist)
                                pub  <ns>/<c>/odom     nav_msgs/Odometry
    imu_sensor_broadcaster      pub  <ns>/<c>/imu      sensor_msgs/Imu
    force_torque_sensor_bc.     pub  <ns>/<c>/wrench   geometry_msgs/WrenchStamped

control_msgs is not part of ROS 2's common interfaces, so the trajectory controller's
state (control_msgs/JointTrajectoryControllerState upstream) is three JointState
messages with one stamp: `reference` (desired position, velocity; effort carries the
desired acceleration), `feedback` (measured position, velocity) and `error` (reference
minus feedback, position and velocity).

Subscriptions only parse and stash messages (they run on the bridge's executor thread);
the binding hands everything that arrived in a period to each input's `apply` at once, in
the loop thread, then runs the controllers, then publishes at the bridge's publish rate
to the worlds whose topics have subscribers. A rejected message is logged, naming the
topic and the reason, and leaves the world as it was.
"""

from __future__ import annotations

import math
import threading
import time as wallclock
from typing import Any

import numpy as np

from batchsim.controllers import ControllerManager
from batchsim.controllers.topics import Input, MessageKind, Output, trajectory_batch
from ros_bridge.messages import MESSAGE_TYPES, Built, fill_message, new_message, parse_row, parse_trajectory

LOG_INTERVAL = 2.0  # wall seconds between two log lines about one topic and reason
SUBSCRIBER_REFRESH = 50  # periods between re-reading which publishers have subscribers


class ControllerBinding:
    """The controllers' topics and the controller manager's turn in the loop.

    Registered with `bridge.add_participant`, so it runs right after the bridge every
    control period: deliver stashed messages, update every controller, publish.
    """

    def __init__(self, bridge: Any, manager: ControllerManager):
        self.bridge = bridge
        self.manager = manager
        self.node = bridge.node
        self.qos = bridge.qos
        self.publish_every = int(getattr(bridge, "publish_every", 1))
        self._lock = threading.Lock()
        self._log_last: dict[str, float] = {}
        self._period = 0
        # per input: (input, topic per world, what arrived: [(world, row or trajectory)])
        self._inputs: list[tuple[Input, list[str], list[tuple[int, Any]]]] = []
        # per output: (output, [(publisher, world, message)]) and those with subscribers
        self._outputs: list[tuple[Output, list[tuple[Any, int, Built]]]] = []
        self._active: list[tuple[Output, list[tuple[Any, int, Built]]]] = []
        self._subscriptions: list[Any] = []
        for c in manager:
            bridge.claim(c.name, c.command_interfaces)
            topics = c.topics()
            if topics.replaces_joint_states:
                bridge.publish_joint_states = False
            for output in topics.outputs:
                self._bind_output(output)
            for input in topics.inputs:
                self._bind_input(input)
        self._refresh()

    # --- topics ---
    def _bind_output(self, output: Output) -> None:
        entries = []
        for w, ns in enumerate(self.bridge.namespaces):
            pub = self.node.create_publisher(MESSAGE_TYPES[output.kind], f"/{ns}/{output.topic}", self.qos)
            entries.append((pub, w, new_message(output, ns)))
        self._outputs.append((output, entries))

    def _bind_input(self, input: Input) -> None:
        stash: list[tuple[int, Any]] = []
        topics = [f"/{ns}/{input.topic}" for ns in self.bridge.namespaces]
        parse = (
            parse_trajectory
            if input.kind is MessageKind.JOINT_TRAJECTORY
            else lambda msg: parse_row(input, msg)
        )
        for w, topic in enumerate(topics):

            def callback(msg: Any, w: int = w, topic: str = topic) -> None:
                try:
                    value = parse(msg)
                except (ValueError, TypeError) as e:
                    self._warn(topic, str(e))
                    return
                with self._lock:
                    stash.append((w, value))

            self._subscriptions.append(
                self.node.create_subscription(MESSAGE_TYPES[input.kind], topic, callback, self.qos)
            )
        self._inputs.append((input, topics, stash))

    # --- the loop thread ---
    def update(self, sim: Any, time: float, period: float) -> None:
        for input, topics, stash in self._inputs:
            if stash:
                with self._lock:
                    arrived = stash[:]
                    stash.clear()
                self._apply(input, topics, arrived)
        self.manager.update(sim, time, period)
        k = self._period
        self._period = k + 1
        if k % SUBSCRIBER_REFRESH == 0:
            self._refresh()
        if k % self.publish_every == 0 and self._active:
            stamp = self.bridge.stamp(time)
            for output, entries in self._active:
                values = output.read()
                for pub, w, built in entries:
                    pub.publish(fill_message(output.kind, built, {f: v[w] for f, v in values.items()}, stamp))

    def _apply(self, input: Input, topics: list[str], arrived: list[tuple[int, Any]]) -> None:
        worlds = [w for w, _ in arrived]
        if input.kind is MessageKind.JOINT_TRAJECTORY:
            too_long = [
                k for k, (_, t) in enumerate(arrived) if input.max_points and len(t[1]) > input.max_points
            ]
            for k in too_long:
                self._warn(topics[worlds[k]], f"{len(arrived[k][1][1])} points, more than {input.max_points}")
            skip = set(too_long)
            keep = [k for k in range(len(arrived)) if k not in skip]
            batch, index, rejected = trajectory_batch(
                input.joints, [(worlds[k], *arrived[k][1]) for k in keep]
            )
            rejected = [(keep[k], why) for k, why in rejected]
            rejected += [(keep[index[k]], why) for k, why in input.apply(batch)]
        else:
            rows = np.array([row for _, row in arrived], dtype=np.float64)
            rejected = input.apply(np.array(worlds, dtype=np.int64), rows)
        for k, why in rejected:
            self._warn(topics[worlds[k]], why)

    def _refresh(self) -> None:
        self._active = []
        for output, entries in self._outputs:
            listened = [e for e in entries if e[0].get_subscription_count() > 0]
            if listened:
                self._active.append((output, listened))

    def _warn(self, topic: str, reason: str) -> None:
        key = f"{topic}|{reason.split(' ', 1)[0]}"
        now = wallclock.monotonic()
        if now - self._log_last.get(key, -math.inf) >= LOG_INTERVAL:
            self._log_last[key] = now
            self.node.get_logger().warning(f"{topic}: rejected: {reason}")

    def close(self) -> None:
        for _, entries in self._outputs:
            for pub, _, _ in entries:
                self.node.destroy_publisher(pub)
        for sub in self._subscriptions:
            self.node.destroy_subscription(sub)
        self._outputs, self._active, self._subscriptions = [], [], []


def bind_controllers(bridge: Any, manager: ControllerManager) -> ControllerBinding:
    """Give every controller its topics on `bridge` and run the manager after the bridge each period."""
    binding = ControllerBinding(bridge, manager)
    bridge.add_participant(binding)
    return binding
