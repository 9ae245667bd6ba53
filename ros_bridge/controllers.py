"""The ROS topics of batchsim's controllers, under each world's namespace.

`bind_controllers(bridge, manager)` gives every controller in `manager` the topics of its
ros2_control counterpart, for every world `<ns>`:

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

Subscriptions only stash messages (they run on the bridge's executor thread); the
binding hands them to the controllers at the start of its update, in the loop thread,
then runs the controllers, then publishes at the bridge's publish rate to the worlds
whose topics have subscribers. A rejected message is logged, naming the topic, and
leaves the world as it was.
"""

from __future__ import annotations

import array
import math
import threading
import time as wallclock
from collections.abc import Callable
from typing import Any

import numpy as np
from geometry_msgs.msg import Twist, TwistStamped, WrenchStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray
from trajectory_msgs.msg import JointTrajectory

from batchsim.controllers import (
    ControllerManager,
    DiffDriveController,
    ForceTorqueSensorBroadcaster,
    ForwardCommandController,
    IMUSensorBroadcaster,
    JointStateBroadcaster,
    JointTrajectoryController,
)

LOG_INTERVAL = 2.0  # wall seconds between two log lines about one topic
SUBSCRIBER_REFRESH = 50  # periods between re-reading which publishers have subscribers


def _seconds(stamp: Any) -> float:
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def _field_view(msg: Any, field: str, n: int) -> np.ndarray:
    """A float64[] field of `msg`, sized n, as a NumPy view that writes into the message.

    rclpy copies an array.array on assignment, so the view is taken of the stored copy.
    """
    setattr(msg, field, array.array("d", bytes(8 * n)))
    return np.frombuffer(getattr(msg, field), dtype=np.float64)


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
        self._stash: list[tuple[Callable[..., None], int, str, tuple]] = []
        self._log_last: dict[str, float] = {}
        self._period = 0
        # (publisher, world, fill(world, stamp) -> message) per topic and world
        self._outputs: list[tuple[Any, int, Callable[[int, Any], Any]]] = []
        self._active: list[tuple[Any, int, Callable[[int, Any], Any]]] = []
        self._subscriptions: list[Any] = []
        for c in manager:
            bridge.claim(c.name, c.command_interfaces)
            if isinstance(c, JointStateBroadcaster):
                self._bind_joint_states(c)
            elif isinstance(c, ForwardCommandController):
                self._bind_forward(c)
            elif isinstance(c, JointTrajectoryController):
                self._bind_trajectory(c)
            elif isinstance(c, DiffDriveController):
                self._bind_diff_drive(c)
            elif isinstance(c, IMUSensorBroadcaster):
                self._bind_imu(c)
            elif isinstance(c, ForceTorqueSensorBroadcaster):
                self._bind_wrench(c)
        self._refresh()

    # --- topics ---
    def _topic(self, world: int, *parts: str) -> str:
        return "/" + "/".join((self.bridge.namespaces[world], *parts))

    def _subscribe(
        self,
        msg_type: type,
        world: int,
        topic: str,
        handler: Callable[..., None],
        parse: Callable[[Any], tuple],
    ) -> None:
        def callback(msg: Any) -> None:
            try:
                args = parse(msg)
            except (ValueError, TypeError) as e:
                self._warn(topic, f"{topic}: rejected: {e}")
                return
            with self._lock:
                self._stash.append((handler, world, topic, args))

        self._subscriptions.append(self.node.create_subscription(msg_type, topic, callback, self.qos))

    def _publish(self, msg_type: type, world: int, topic: str, fill: Callable[[int, Any], Any]) -> None:
        pub = self.node.create_publisher(msg_type, topic, self.qos)
        self._outputs.append((pub, world, fill))

    def _joint_state_writer(
        self, names: list[str], sources: list[np.ndarray | None]
    ) -> Callable[[int, Any], Any]:
        """A fill function for a JointState of fixed names whose fields are rows of (nworld, n) arrays."""
        cache: dict[int, tuple[JointState, list[np.ndarray | None]]] = {}

        def fill(world: int, stamp: Any) -> JointState:
            if world not in cache:
                msg = JointState()
                msg.name = list(names)
                views = []
                for field, src in zip(("position", "velocity", "effort"), sources, strict=True):
                    if src is None:
                        views.append(None)
                        continue
                    views.append(_field_view(msg, field, len(names)))
                cache[world] = (msg, views)
            msg, views = cache[world]
            msg.header.stamp = stamp
            for view, src in zip(views, sources, strict=True):
                if view is not None:
                    view[:] = src[world]
            return msg

        return fill

    def _bind_joint_states(self, c: JointStateBroadcaster) -> None:
        fill = self._joint_state_writer(c.names, [c.position, c.velocity, c.effort])
        for w in range(c.nworld):
            topic = (
                self._topic(w, c.name, "joint_states")
                if c.use_local_topics
                else self._topic(w, "joint_states")
            )
            self._publish(JointState, w, topic, fill)
        if not c.use_local_topics:
            self.bridge.publish_joint_states = False

    def _bind_forward(self, c: ForwardCommandController) -> None:
        for w in range(c.nworld):
            self._subscribe(
                Float64MultiArray,
                w,
                self._topic(w, c.name, "commands"),
                c.set_commands,
                lambda msg: (np.array(msg.data, dtype=np.float64),),
            )

    def _bind_trajectory(self, c: JointTrajectoryController) -> None:
        def parse(msg: JointTrajectory) -> tuple:
            points = msg.points
            names = list(msg.joint_names)
            times = [_seconds(p.time_from_start) for p in points]
            positions = [list(p.positions) for p in points]
            has_v = any(len(p.velocities) for p in points)
            has_a = any(len(p.accelerations) for p in points)
            velocities = [list(p.velocities) for p in points] if has_v else None
            accelerations = [list(p.accelerations) for p in points] if has_a else None
            if has_v and any(len(p.velocities) != len(names) for p in points):
                raise ValueError(f"every point's velocities must have {len(names)} values or none")
            if has_a and any(len(p.accelerations) != len(names) for p in points):
                raise ValueError(f"every point's accelerations must have {len(names)} values or none")
            if any(len(p) != len(names) for p in positions):
                raise ValueError(f"every point's positions must have {len(names)} values")
            return names, times, positions, velocities, accelerations, _seconds(msg.header.stamp)

        for w in range(c.nworld):
            self._subscribe(
                JointTrajectory, w, self._topic(w, c.name, "joint_trajectory"), c.set_trajectory, parse
            )
        parts = {
            "reference": [c.reference_position, c.reference_velocity, c.reference_acceleration],
            "feedback": [c.feedback_position, c.feedback_velocity, None],
            "error": [c.error_position, c.error_velocity, None],
        }
        for part, sources in parts.items():
            fill = self._joint_state_writer(c.joints, sources)
            for w in range(c.nworld):
                self._publish(JointState, w, self._topic(w, c.name, "controller_state", part), fill)

    def _bind_diff_drive(self, c: DiffDriveController) -> None:
        if c.use_stamped_vel:

            def parse(msg: TwistStamped) -> tuple:
                return msg.twist.linear.x, msg.twist.angular.z, _seconds(msg.header.stamp)

            msg_type: type = TwistStamped
        else:

            def parse(msg: Twist) -> tuple:
                return msg.linear.x, msg.angular.z

            msg_type = Twist
        for w in range(c.nworld):
            self._subscribe(msg_type, w, self._topic(w, c.name, "cmd_vel"), c.set_cmd_vel, parse)

        msgs: dict[int, Odometry] = {}

        def fill(world: int, stamp: Any) -> Odometry:
            msg = msgs.get(world)
            if msg is None:
                msg = msgs[world] = Odometry()
                msg.header.frame_id = c.odom_frame_id
                msg.child_frame_id = c.base_frame_id
                pose_cov = np.zeros(36)
                twist_cov = np.zeros(36)
                pose_cov[::7] = c.pose_covariance_diagonal
                twist_cov[::7] = c.twist_covariance_diagonal
                msg.pose.covariance = pose_cov.tolist()
                msg.twist.covariance = twist_cov.tolist()
            msg.header.stamp = stamp
            x, y, yaw = c.odom_pose[world]
            msg.pose.pose.position.x, msg.pose.pose.position.y = float(x), float(y)
            o = msg.pose.pose.orientation
            o.z, o.w = math.sin(0.5 * yaw), math.cos(0.5 * yaw)
            msg.twist.twist.linear.x = float(c.odom_twist[world, 0])
            msg.twist.twist.angular.z = float(c.odom_twist[world, 1])
            return msg

        for w in range(c.nworld):
            self._publish(Odometry, w, self._topic(w, c.name, "odom"), fill)

    def _bind_imu(self, c: IMUSensorBroadcaster) -> None:
        msgs: dict[int, Imu] = {}

        def fill(world: int, stamp: Any) -> Imu:
            msg = msgs.get(world)
            if msg is None:
                msg = msgs[world] = Imu()
                msg.header.frame_id = c.frame_id
                for part in ("orientation", "angular_velocity", "linear_acceleration"):
                    cov = list(c.covariance[part])
                    if not getattr(c, f"has_{part}"):
                        cov[0] = -1.0  # REP 145: this part is not provided
                    setattr(msg, f"{part}_covariance", cov)
            msg.header.stamp = stamp
            q = c.orientation[world]
            o = msg.orientation
            o.x, o.y, o.z, o.w = (float(v) for v in q)
            g = c.angular_velocity[world]
            msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z = (float(v) for v in g)
            a = c.linear_acceleration[world]
            la = msg.linear_acceleration
            la.x, la.y, la.z = (float(v) for v in a)
            return msg

        for w in range(c.nworld):
            self._publish(Imu, w, self._topic(w, c.name, "imu"), fill)

    def _bind_wrench(self, c: ForceTorqueSensorBroadcaster) -> None:
        msgs: dict[int, WrenchStamped] = {}

        def fill(world: int, stamp: Any) -> WrenchStamped:
            msg = msgs.get(world)
            if msg is None:
                msg = msgs[world] = WrenchStamped()
                msg.header.frame_id = c.frame_id
            msg.header.stamp = stamp
            f, t = msg.wrench.force, msg.wrench.torque
            f.x, f.y, f.z, t.x, t.y, t.z = (float(v) for v in c.wrench[world])
            return msg

        for w in range(c.nworld):
            self._publish(WrenchStamped, w, self._topic(w, c.name, "wrench"), fill)

    # --- the loop thread ---
    def update(self, sim: Any, time: float, period: float) -> None:
        if self._stash:
            with self._lock:
                stash, self._stash = self._stash, []
            for handler, world, topic, args in stash:
                try:
                    handler(world, *args)
                except ValueError as e:
                    self._warn(topic, f"{topic}: rejected: {e}")
        self.manager.update(sim, time, period)
        k = self._period
        self._period = k + 1
        if k % SUBSCRIBER_REFRESH == 0:
            self._refresh()
        if k % self.publish_every == 0 and self._active:
            stamp = self.bridge.stamp(time)
            for pub, world, fill in self._active:
                pub.publish(fill(world, stamp))

    def _refresh(self) -> None:
        self._active = [o for o in self._outputs if o[0].get_subscription_count() > 0]

    def _warn(self, key: str, text: str) -> None:
        now = wallclock.monotonic()
        if now - self._log_last.get(key, -math.inf) >= LOG_INTERVAL:
            self._log_last[key] = now
            self.node.get_logger().warning(text)

    def close(self) -> None:
        for pub, _, _ in self._outputs:
            self.node.destroy_publisher(pub)
        for sub in self._subscriptions:
            self.node.destroy_subscription(sub)
        self._outputs, self._active, self._subscriptions = [], [], []


def bind_controllers(bridge: Any, manager: ControllerManager) -> ControllerBinding:
    """Give every controller its topics on `bridge` and run the manager after the bridge each period."""
    binding = ControllerBinding(bridge, manager)
    bridge.add_participant(binding)
    return binding
