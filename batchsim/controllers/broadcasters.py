"""The broadcasters: joint states, IMU and force/torque sensors, read from state interfaces.

They claim no command interface; each update copies its state columns into plain
(nworld, ...) arrays that the ROS bridge publishes.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np

from batchsim.controllers.base import Controller, Params
from batchsim.controllers.topics import ControllerTopics, MessageKind, Output
from batchsim.model import RobotSpec
from batchsim.types import as_slice

JOINT_INTERFACES = ("position", "velocity", "effort")


class JointStateBroadcaster(Controller):
    """joint_state_broadcaster/JointStateBroadcaster: sensor_msgs/JointState of every world.

    Parameters (stock): `joints` and `interfaces` narrow what is broadcast (empty: every
    joint and interface); `extra_joints` are published with zeros; `use_local_topics`
    publishes on `<ns>/<controller>/joint_states` instead of `<ns>/joint_states`.

    Attributes:
      names: joint names, in message order (extra joints last).
      position, velocity, effort: (nworld, njoint); NaN where a joint lacks the interface,
        as ros2_control fills a missing value.
    """

    TYPE: ClassVar[str] = "joint_state_broadcaster/JointStateBroadcaster"
    ACCEPTED = (*Controller.ACCEPTED, "map_interface_to_joint_state", "frame_id")

    def __init__(self, name: str, params: Params, spec: RobotSpec, nworld: int):
        super().__init__(name, params, spec, nworld)
        joints = params.string_list("joints", [])
        interfaces = params.string_list("interfaces", [])
        self.check_joints("joints", joints)
        for i in interfaces:
            if i not in JOINT_INTERFACES:
                raise params.error(
                    "interfaces",
                    f"unknown interface {i!r} (joint_states carries: {', '.join(JOINT_INTERFACES)})",
                )
        self.extra_joints = params.string_list("extra_joints", [])
        self.use_local_topics = params.boolean("use_local_topics", False)
        if not joints or not interfaces:  # stock: both empty -> everything available
            joints = [j.name for j in spec.joints]
            interfaces = list(JOINT_INTERFACES)
        state = self._state_names
        self.names = [j for j in joints if any(f"{j}/{i}" in state for i in interfaces)] + self.extra_joints
        n = len(self.names)
        self.position = np.full((self.nworld, n), np.nan)
        self.velocity = np.full((self.nworld, n), np.nan)
        self.effort = np.full((self.nworld, n), np.nan)
        # (its array, message columns, state columns), as slices where they step evenly
        self._gather: list[tuple[np.ndarray, slice | np.ndarray, slice | np.ndarray]] = []
        for i in interfaces:
            rows = [k for k, j in enumerate(self.names[: n - len(self.extra_joints)]) if f"{j}/{i}" in state]
            if rows:
                cols = self.state_columns("interfaces", [f"{self.names[k]}/{i}" for k in rows])
                self._gather.append((getattr(self, i), as_slice(np.array(rows, dtype=np.intp)), as_slice(cols)))
        extra = slice(n - len(self.extra_joints), n)
        for a in (self.position, self.velocity, self.effort):
            a[:, extra] = 0.0

    def update(self, sim: Any, time: float, period: float) -> None:
        state = sim.state
        for out, rows, cols in self._gather:
            out[:, rows] = state[:, cols]

    def topics(self) -> ControllerTopics:
        """`<ns>/joint_states` (with use_local_topics `<ns>/<controller>/joint_states`); a robot of a
        world of several: `<ns>/<robot>/joint_states`."""
        topic = f"{self.name}/joint_states" if self.use_local_topics else f"{self.namespace}joint_states"
        fields = {"position": self.position, "velocity": self.velocity, "effort": self.effort}
        return ControllerTopics(
            self.name,
            outputs=(Output(topic, MessageKind.JOINT_STATE, lambda: fields, names=tuple(self.names)),),
            replaces_joint_states=not self.use_local_topics,
        )


def _sensor_columns(ctrl: Controller, key: str, sensor_name: str, fields: Sequence[str]) -> list[int | None]:
    """State columns of `fields` of a named sensor, as ros2_control's semantic components read them.

    `<sensor_name>/<field>` if the model exposes it; else the field from any MJCF sensor
    attached to the same site or frame as `sensor_name` (a site's name, or one of its
    sensors' names), since MuJoCo splits an IMU or a force/torque pair into one sensor per
    quantity. None for a field no sensor provides.
    """
    state = ctrl._state_names
    sensors = ctrl.spec.sensors
    anchors = {sensor_name} | {s.objname for s in sensors if s.name == sensor_name and s.objname}
    out: list[int | None] = []
    for f in fields:
        name = f"{sensor_name}/{f}"
        if name not in state:
            name = next(
                (
                    f"{s.name}/{f}"
                    for s in sensors
                    if (s.objname in anchors or s.name == sensor_name) and f"{s.name}/{f}" in state
                ),
                None,
            )
        out.append(None if name is None else int(ctrl.state_columns(key, [name])[0]))
    return out


class IMUSensorBroadcaster(Controller):
    """imu_sensor_broadcaster/IMUSensorBroadcaster: sensor_msgs/Imu of every world.

    Parameters (stock): `sensor_name` (a ros2_control sensor, an MJCF sensor, or the site
    that MJCF framequat / gyro / accelerometer sensors sit on), `frame_id`,
    `static_covariance_orientation`, `static_covariance_angular_velocity`,
    `static_covariance_linear_acceleration` (9 values each).

    Attributes:
      orientation: (nworld, 4) x, y, z, w (ROS order; MuJoCo's w first is converted).
      angular_velocity, linear_acceleration: (nworld, 3).
      has_orientation, has_angular_velocity, has_linear_acceleration: which parts a sensor
        provides; a missing part is published with covariance[0] = -1 (REP 145).
    """

    TYPE: ClassVar[str] = "imu_sensor_broadcaster/IMUSensorBroadcaster"
    FIELDS = (
        [f"orientation.{c}" for c in "xyzw"]
        + [f"angular_velocity.{c}" for c in "xyz"]
        + [f"linear_acceleration.{c}" for c in "xyz"]
    )

    def __init__(self, name: str, params: Params, spec: RobotSpec, nworld: int):
        super().__init__(name, params, spec, nworld)
        self.sensor_name = params.string("sensor_name")
        self.frame_id = params.string("frame_id", self.sensor_name)
        self.covariance = {
            part: self._covariance(params, f"static_covariance_{part}")
            for part in ("orientation", "angular_velocity", "linear_acceleration")
        }
        cols = _sensor_columns(self, "sensor_name", self.sensor_name, self.FIELDS)
        parts = {"orientation": cols[0:4], "angular_velocity": cols[4:7], "linear_acceleration": cols[7:10]}
        for part, c in parts.items():
            setattr(self, f"has_{part}", all(x is not None for x in c))
        if not any(getattr(self, f"has_{p}") for p in parts):
            raise params.error(
                "sensor_name",
                f"the model has no IMU sensor {self.sensor_name!r} (no framequat, gyro or accelerometer "
                f"named so or on a site of that name; sensors: {', '.join(s.name for s in spec.sensors) or 'none'})",
            )
        self._parts = [
            (part, as_slice(np.array(c, dtype=np.intp))) for part, c in parts.items() if all(x is not None for x in c)
        ]
        self.orientation = np.zeros((self.nworld, 4))
        self.orientation[:, 3] = 1.0
        self.angular_velocity = np.zeros((self.nworld, 3))
        self.linear_acceleration = np.zeros((self.nworld, 3))

    @staticmethod
    def _covariance(params: Params, key: str) -> list[float]:
        value = params.raw(key, [0.0] * 9)
        if (
            not isinstance(value, list)
            or len(value) != 9
            or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
        ):
            raise params.error(key, f"must be a list of 9 numbers, got {value!r}")
        return [float(v) for v in value]

    def update(self, sim: Any, time: float, period: float) -> None:
        state = sim.state
        for part, cols in self._parts:
            getattr(self, part)[:] = state[:, cols]

    def topics(self) -> ControllerTopics:
        """`<ns>/<controller>/imu`; a part the sensor lacks has covariance[0] = -1 (REP 145)."""
        fields = {
            "orientation": self.orientation,
            "angular_velocity": self.angular_velocity,
            "linear_acceleration": self.linear_acceleration,
        }
        covariance = {}
        for part, cov in self.covariance.items():
            cov = list(cov)
            if not getattr(self, f"has_{part}"):
                cov[0] = -1.0
            covariance[part] = tuple(cov)
        imu = Output(f"{self.name}/imu", MessageKind.IMU, lambda: fields, frame_id=self.frame_id, covariance=covariance)
        return ControllerTopics(self.name, outputs=(imu,))


class ForceTorqueSensorBroadcaster(Controller):
    """force_torque_sensor_broadcaster/ForceTorqueSensorBroadcaster: geometry_msgs/WrenchStamped.

    Parameters (stock): `sensor_name` (a ros2_control sensor, an MJCF force or torque
    sensor, or the site they sit on) or `interface_names.force.x` ... `.torque.z` (full
    state interface names), and `frame_id`.

    Attributes:
      force, torque: (nworld, 3); zeros for a half the sensor does not have.
    """

    TYPE: ClassVar[str] = "force_torque_sensor_broadcaster/ForceTorqueSensorBroadcaster"
    FIELDS = [f"force.{c}" for c in "xyz"] + [f"torque.{c}" for c in "xyz"]

    def __init__(self, name: str, params: Params, spec: RobotSpec, nworld: int):
        super().__init__(name, params, spec, nworld)
        self.sensor_name = params.string("sensor_name", "")
        explicit = {f: params.string(f"interface_names.{f}", "") for f in self.FIELDS}
        if self.sensor_name:
            cols = _sensor_columns(self, "sensor_name", self.sensor_name, self.FIELDS)
            key = "sensor_name"
        elif any(explicit.values()):
            cols = [
                None if not n else int(self.state_columns(f"interface_names.{f}", [n])[0])
                for f, n in explicit.items()
            ]
            key = "interface_names"
        else:
            raise params.error("sensor_name", "missing (give sensor_name or interface_names.force.x ...)")
        if all(c is None for c in cols):
            raise params.error(
                key,
                f"the model has no force/torque sensor {self.sensor_name!r} (no force or torque sensor "
                f"named so or on a site of that name; sensors: {', '.join(s.name for s in spec.sensors) or 'none'})",
            )
        self.frame_id = params.string("frame_id", self.sensor_name)
        self._rows = as_slice(np.array([k for k, c in enumerate(cols) if c is not None], dtype=np.intp))
        self._cols = as_slice(np.array([c for c in cols if c is not None], dtype=np.intp))
        self.wrench = np.zeros((self.nworld, 6))

    @property
    def force(self) -> np.ndarray:
        return self.wrench[:, :3]

    @property
    def torque(self) -> np.ndarray:
        return self.wrench[:, 3:]

    def update(self, sim: Any, time: float, period: float) -> None:
        self.wrench[:, self._rows] = sim.state[:, self._cols]

    def topics(self) -> ControllerTopics:
        """`<ns>/<controller>/wrench`."""
        fields = {"force": self.force, "torque": self.torque}
        wrench = Output(f"{self.name}/wrench", MessageKind.WRENCH_STAMPED, lambda: fields, frame_id=self.frame_id)
        return ControllerTopics(self.name, outputs=(wrench,))
