"""ROS messages built in bulk from arrays, and parsed into rows and trajectories.

    bulk = BulkMessages(spec, ["world_0", "world_1"])   # once: every world's serialized template
    bulk.fill(values, sec, nanosec)                       # every publish: (nrow, nvalue) float64
    publisher.publish(bulk.payload(row))                  # CDR bytes, no message object
    row = parse_row(input, msg)                           # an incoming Twist, Float64MultiArray, ...
    traj = parse_trajectory(msg)                          # an incoming JointTrajectory

A message's serialized layout is fixed per world once its names and frames are set: only
the stamp and the float64 values change. So each world's message is serialized once, with
marker values, to find where each value lies; every publish then writes the values of all
worlds into their byte rows with one NumPy assignment and hands rclpy the bytes
(`Publisher.publish(bytes)`), which skips building a Python message and converting it,
field by field, per world and period. benchmarks/messages.py measures both ways.

`new_message` / `fill_message` build one message object per world instead (the other way,
kept for that comparison and for callers that want message objects).
"""

from __future__ import annotations

import array
import importlib
import struct
from collections.abc import Sequence
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped, Twist, TwistStamped, WrenchStamped
from nav_msgs.msg import Odometry
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray
from trajectory_msgs.msg import JointTrajectory

from batchsim.controllers.topics import Input, MessageKind, Output
from ros_bridge.naming import expand_frame
from ros_bridge.plan import OutputSpec

MESSAGE_TYPES: dict[MessageKind, type] = {
    MessageKind.JOINT_STATE: JointState,
    MessageKind.IMU: Imu,
    MessageKind.WRENCH_STAMPED: WrenchStamped,
    MessageKind.ODOMETRY: Odometry,
    MessageKind.POSE_STAMPED: PoseStamped,
    MessageKind.FLOAT64_MULTI_ARRAY: Float64MultiArray,
    MessageKind.TWIST: Twist,
    MessageKind.TWIST_STAMPED: TwistStamped,
    MessageKind.JOINT_TRAJECTORY: JointTrajectory,
}

# a parsed JointTrajectory: joint_names, times (npoint,), positions (npoint, nnamed),
# velocities or None, accelerations or None, header stamp in seconds
Trajectory = tuple[list[str], np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None, float]


def seconds(stamp: Any) -> float:
    """builtin_interfaces/Time in seconds."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def float64_view(msg: Any, field: str, n: int) -> np.ndarray:
    """A float64[] field of `msg`, sized n, as a NumPy view that writes into the message.

    rclpy copies an array.array on assignment, so the view is taken of the stored copy.
    """
    setattr(msg, field, array.array("d", bytes(8 * n)))
    return np.frombuffer(getattr(msg, field), dtype=np.float64)


class Built:
    """One world's message of an Output, with views of its float64 sequences."""

    __slots__ = ("msg", "views")

    def __init__(self, msg: Any, views: dict[str, np.ndarray]):
        self.msg = msg
        self.views = views


def new_message(output: Output, namespace: str) -> Built:
    """A world's message of `output`, its constant parts (names, frames, covariances) set."""
    msg = MESSAGE_TYPES[output.kind]()
    views: dict[str, np.ndarray] = {}
    frame = expand_frame(output.frame_id, namespace)
    if hasattr(msg, "header"):
        msg.header.frame_id = frame
    kind = output.kind
    if kind is MessageKind.JOINT_STATE:
        msg.name = list(output.names)
        # every field the output declares gets a view; read() may give a subset per call
        for field in ("position", "velocity", "effort"):
            views[field] = float64_view(msg, field, len(output.names))
    elif kind is MessageKind.IMU:
        for part in ("orientation", "angular_velocity", "linear_acceleration"):
            if part in output.covariance:
                setattr(msg, f"{part}_covariance", [float(v) for v in output.covariance[part]])
    elif kind is MessageKind.ODOMETRY:
        msg.child_frame_id = expand_frame(output.child_frame_id, namespace)
        if "pose" in output.covariance:
            msg.pose.covariance = [float(v) for v in output.covariance["pose"]]
        if "twist" in output.covariance:
            msg.twist.covariance = [float(v) for v in output.covariance["twist"]]
    return Built(msg, views)


def _xyz(target: Any, row: Any) -> None:
    target.x, target.y, target.z = float(row[0]), float(row[1]), float(row[2])


def _xyzw(target: Any, row: Any) -> None:
    target.x, target.y, target.z, target.w = float(row[0]), float(row[1]), float(row[2]), float(row[3])


def fill_message(kind: MessageKind, built: Built, rows: dict[str, np.ndarray], stamp: Any) -> Any:
    """Write one world's rows (field -> (width,)) and the stamp into its message; returns it."""
    msg = built.msg
    if kind is MessageKind.JOINT_STATE:
        msg.header.stamp = stamp
        for field, view in built.views.items():
            row = rows.get(field)
            if row is None:
                view.fill(np.nan)
            else:
                view[:] = row
    elif kind is MessageKind.IMU:
        msg.header.stamp = stamp
        _xyzw(msg.orientation, rows["orientation"])
        _xyz(msg.angular_velocity, rows["angular_velocity"])
        _xyz(msg.linear_acceleration, rows["linear_acceleration"])
    elif kind is MessageKind.WRENCH_STAMPED:
        msg.header.stamp = stamp
        _xyz(msg.wrench.force, rows["force"])
        _xyz(msg.wrench.torque, rows["torque"])
    elif kind is MessageKind.ODOMETRY:
        msg.header.stamp = stamp
        _xyz(msg.pose.pose.position, rows["position"])
        _xyzw(msg.pose.pose.orientation, rows["orientation"])
        _xyz(msg.twist.twist.linear, rows["linear"])
        _xyz(msg.twist.twist.angular, rows["angular"])
    elif kind is MessageKind.POSE_STAMPED:
        msg.header.stamp = stamp
        _xyz(msg.pose.position, rows["position"])
        _xyzw(msg.pose.orientation, rows["orientation"])
    else:
        raise ValueError(f"{kind.value} is not an output message kind")
    return msg


def parse_row(input: Input, msg: Any) -> np.ndarray:
    """A fixed-size input message as its row; ValueError naming what is wrong."""
    kind = input.kind
    if kind is MessageKind.FLOAT64_MULTI_ARRAY:
        row = np.asarray(msg.data, dtype=np.float64)
        if row.shape != (input.width,):
            raise ValueError(f"{row.size} values, expected {input.width}")
        return row
    if kind is MessageKind.TWIST or kind is MessageKind.TWIST_STAMPED:
        twist = msg if kind is MessageKind.TWIST else msg.twist
        values = [
            twist.linear.x,
            twist.linear.y,
            twist.linear.z,
            twist.angular.x,
            twist.angular.y,
            twist.angular.z,
        ]
        if kind is MessageKind.TWIST_STAMPED:
            values.append(seconds(msg.header.stamp))
        return np.array(values, dtype=np.float64)
    raise ValueError(f"{kind.value} is not a fixed-size input kind")


def parse_trajectory(msg: JointTrajectory) -> Trajectory:
    """A JointTrajectory as arrays in its own joint order; ValueError for ragged points."""
    names = list(msg.joint_names)
    n = len(names)
    points = msg.points
    if any(len(p.positions) != n for p in points):
        raise ValueError(f"every point's positions must have {n} values")
    has_v = any(len(p.velocities) for p in points)
    has_a = any(len(p.accelerations) for p in points)
    if has_v and any(len(p.velocities) != n for p in points):
        raise ValueError(f"every point's velocities must have {n} values or none")
    if has_a and any(len(p.accelerations) != n for p in points):
        raise ValueError(f"every point's accelerations must have {n} values or none")
    times = np.array([seconds(p.time_from_start) for p in points], dtype=np.float64)
    positions = np.array([p.positions for p in points], dtype=np.float64).reshape(len(points), n)
    velocities = np.array([p.velocities for p in points], dtype=np.float64) if has_v else None
    accelerations = np.array([p.accelerations for p in points], dtype=np.float64) if has_a else None
    return names, times, positions, velocities, accelerations, seconds(msg.header.stamp)


# --- messages in bulk ---


def _vec(path: str) -> tuple[str, ...]:
    return (f"{path}.x", f"{path}.y", f"{path}.z")


def _quat(path: str) -> tuple[str, ...]:
    return (f"{path}.x", f"{path}.y", f"{path}.z", f"{path}.w")


#: per message type, what each named field of an OutputSpec fills: a float64 sequence
#: (a path, sized by the field's columns) or float64 scalars (a tuple of paths, one per column)
FIELD_PATHS: dict[str, dict[str, str | tuple[str, ...]]] = {
    "sensor_msgs/msg/JointState": {"position": "position", "velocity": "velocity", "effort": "effort"},
    "sensor_msgs/msg/Imu": {
        "orientation": _quat("orientation"),
        "angular_velocity": _vec("angular_velocity"),
        "linear_acceleration": _vec("linear_acceleration"),
    },
    "geometry_msgs/msg/WrenchStamped": {"force": _vec("wrench.force"), "torque": _vec("wrench.torque")},
    "nav_msgs/msg/Odometry": {
        "position": _vec("pose.pose.position"),
        "orientation": _quat("pose.pose.orientation"),
        "linear": _vec("twist.twist.linear"),
        "angular": _vec("twist.twist.angular"),
    },
    "geometry_msgs/msg/PoseStamped": {"position": _vec("pose.position"), "orientation": _quat("pose.orientation")},
    "control_msgs/msg/JointTrajectoryControllerState": {
        f"{part}_{quantity}": f"{part}.{quantity}"
        for part in ("reference", "feedback", "error", "output")
        for quantity in ("positions", "velocities", "accelerations")
    },
    "std_msgs/msg/Float64": {"data": ("data",)},
    "std_msgs/msg/Float64MultiArray": {"data": "data"},
}

#: per message type, the constant covariance arrays an OutputSpec may set
COVARIANCE_PATHS: dict[str, dict[str, str]] = {
    "sensor_msgs/msg/Imu": {
        "orientation": "orientation_covariance",
        "angular_velocity": "angular_velocity_covariance",
        "linear_acceleration": "linear_acceleration_covariance",
    },
    "nav_msgs/msg/Odometry": {"pose": "pose.covariance", "twist": "twist.covariance"},
}

#: per message type, the field OutputSpec.names fills (default: JointState's `name`)
NAME_PATHS: dict[str, str] = {"control_msgs/msg/JointTrajectoryControllerState": "joint_names"}
#: per message type, constant fields every message carries
CONSTANTS: dict[str, dict[str, Any]] = {"control_msgs/msg/JointTrajectoryControllerState": {"speed_scaling_factor": 1.0}}

_STAMP_SEC, _STAMP_NANOSEC = 0x5A3C5A3C, 0x2A5C2A5C  # markers: where the stamp lies
_CLOCK = struct.Struct("<4siI")
_CDR_LE = b"\x00\x01\x00\x00"  # the encapsulation header of plain little-endian CDR


def message_type(name: str) -> type:
    """The message class of "pkg/msg/Name"."""
    package, _, cls = name.split("/")
    return getattr(importlib.import_module(f"{package}.msg"), cls)


def clock_payload(sec: int, nanosec: int) -> bytes:
    """A rosgraph_msgs/Clock, serialized."""
    return _CLOCK.pack(_CDR_LE, sec, nanosec)


def value_markers(n: int) -> np.ndarray:
    """n distinct finite doubles that no message of ours holds by chance (~1e300, tagged)."""
    bits = np.uint64(0x7E3A_5C00_0000_00A5) | (np.arange(n, dtype=np.uint64) << np.uint64(8))
    return bits.view(np.float64)


def _set(msg: Any, path: str, value: Any) -> None:
    *parents, leaf = path.split(".")
    for p in parents:
        msg = getattr(msg, p)
    setattr(msg, leaf, value)


class RowGroup:
    """Worlds whose messages share one byte layout: a byte row each, filled at once."""

    __slots__ = ("rows", "buf", "value_bytes", "stamp_at")

    def __init__(self, rows: list[int], templates: list[bytes], value_at: list[int], stamp_at: int):
        self.rows = np.array(rows, dtype=np.intp)
        self.buf = np.stack([np.frombuffer(t, np.uint8) for t in templates])
        self.value_bytes = (np.asarray(value_at, dtype=np.intp)[:, None] + np.arange(8)).reshape(-1)
        self.stamp_at = stamp_at


class BulkMessages:
    """One output's messages for a range of worlds, as CDR byte rows filled in bulk.

    Args:
      spec: the output.
      namespaces: the worlds' namespaces (row i is namespaces[i]).
    """

    def __init__(self, spec: OutputSpec, namespaces: Sequence[str]):
        self.spec = spec
        cls = message_type(spec.msg_type)
        paths = FIELD_PATHS[spec.msg_type]
        cov_paths = COVARIANCE_PATHS.get(spec.msg_type, {})
        self.nvalue = sum(len(f.columns) for f in spec.fields)
        markers = value_markers(self.nvalue)
        marker_bytes = [m.tobytes() for m in markers]
        by_layout: dict[tuple, tuple[list[int], list[bytes], list[int], int]] = {}
        self.stamped = False
        for row, ns in enumerate(namespaces):
            msg = cls()
            if hasattr(msg, "header"):
                msg.header.frame_id = expand_frame(spec.frame_id, ns)
                msg.header.stamp.sec, msg.header.stamp.nanosec = _STAMP_SEC, _STAMP_NANOSEC
                self.stamped = True
            if spec.child_frame_id:
                msg.child_frame_id = expand_frame(spec.child_frame_id, ns)
            if spec.names:
                _set(msg, NAME_PATHS.get(spec.msg_type, "name"), list(spec.names))
            for path, value in CONSTANTS.get(spec.msg_type, {}).items():
                _set(msg, path, value)
            for part, values in spec.covariance:
                _set(msg, cov_paths[part], [float(v) for v in values])
            k = 0
            for f in spec.fields:
                n = len(f.columns)
                path = paths[f.name]
                if isinstance(path, str):
                    _set(msg, path, array.array("d", markers[k : k + n].tobytes()))
                else:
                    if len(path) != n:
                        raise ValueError(f"{spec.topic}: field {f.name} has {n} columns, {spec.msg_type} takes {len(path)}")
                    for p, m in zip(path, markers[k : k + n], strict=True):
                        _set(msg, p, float(m))
                k += n
            data = bytes(serialize_message(msg))
            value_at = [find_once(data, m, spec.topic) for m in marker_bytes]
            stamp_at = find_once(data, struct.pack("<iI", _STAMP_SEC, _STAMP_NANOSEC), spec.topic) if self.stamped else -1
            key = (len(data), stamp_at, tuple(value_at))
            group = by_layout.setdefault(key, ([], [], value_at, stamp_at))
            group[0].append(row)
            group[1].append(data)
        self.groups = [RowGroup(rows, templates, value_at, stamp_at) for rows, templates, value_at, stamp_at in by_layout.values()]
        self._where: list[tuple[RowGroup, int]] = [None] * len(namespaces)  # type: ignore[list-item]
        for g in self.groups:
            for i, row in enumerate(g.rows.tolist()):
                self._where[row] = (g, i)

    def fill(self, values: np.ndarray, sec: int, nanosec: int) -> None:
        """Write every row's values ((nrow, nvalue) float64, the fields' columns side by
        side) and the stamp into the byte rows."""
        values = np.ascontiguousarray(values, dtype=np.float64)
        stamp = np.frombuffer(struct.pack("<iI", sec, nanosec), np.uint8)
        for g in self.groups:
            if self.nvalue:
                g.buf[:, g.value_bytes] = values[g.rows].view(np.uint8)
            if g.stamp_at >= 0:
                g.buf[:, g.stamp_at : g.stamp_at + 8] = stamp

    def payload(self, row: int) -> bytes:
        """Row `row`'s message, serialized."""
        g, i = self._where[row]
        return g.buf[i].tobytes()


def locate_markers(data: bytes, n: int, what: str) -> np.ndarray:
    """(n,) byte offsets of the float64 markers `value_markers(n)` in a serialized message: each
    must lie exactly once (CDR aligns a float64 to 8 bytes past the 4-byte header)."""
    body = np.frombuffer(data, np.uint8, count=(len(data) - 4) // 8 * 8, offset=4).view("<u8")
    tagged = np.flatnonzero((body & np.uint64(0xFFFF_FF00_0000_00FF)) == np.uint64(0x7E3A_5C00_0000_00A5))
    index = ((body[tagged] >> np.uint64(8)) & np.uint64(0xFFFF_FFFF)).astype(np.int64)
    at = np.full(n, -1, np.int64)
    at[index[index < n]] = 4 + 8 * tagged[index < n]
    if (at < 0).any() or len(np.unique(index)) != len(index) or len(index) != n:
        raise RuntimeError(f"{what}: cannot lay out the serialized message (a marker is missing or repeated)")
    return at


def locate_stamps(data: bytes) -> np.ndarray:
    """Byte offsets of every header stamp marker (`_STAMP_SEC`, `_STAMP_NANOSEC`)."""
    pattern = struct.pack("<iI", _STAMP_SEC, _STAMP_NANOSEC)
    found, at = [], data.find(pattern)
    while at >= 0:
        found.append(at)
        at = data.find(pattern, at + 8)
    return np.array(found, dtype=np.intp)


def set_stamp_marker(stamp: Any) -> None:
    """Mark a builtin_interfaces/Time so that `locate_stamps` finds it once serialized."""
    stamp.sec, stamp.nanosec = _STAMP_SEC, _STAMP_NANOSEC


def stamp_bytes(sec: int, nanosec: int) -> np.ndarray:
    """A stamp as the 8 bytes CDR holds."""
    return np.frombuffer(struct.pack("<iI", sec, nanosec), np.uint8)


def find_once(data: bytes, pattern: bytes, topic: str) -> int:
    """Where `pattern` lies in a serialized message; it must lie there exactly once."""
    at = data.find(pattern)
    if at < 0 or data.find(pattern, at + 1) >= 0:
        raise RuntimeError(f"{topic}: cannot lay out the serialized message (marker found {'twice' if at >= 0 else 'nowhere'})")
    return at
