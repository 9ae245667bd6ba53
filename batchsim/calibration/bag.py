"""The real robot's bag: its joint states per joint over time and the commands its controllers
received, read from a rosbag2 MCAP and checked against the robot and its controllers.

    bag = read_bag("real.mcap", joints=["joint1", ...], inputs={"arm_controller/joint_trajectory":
                   MessageKind.JOINT_TRAJECTORY}, namespace=None)
    bag.times          (nsample,) seconds since the first joint state
    bag.positions      (nsample, njoint) rad or m, NaN where a message left a joint out

Times are on the joint states' clock (their header stamps); a command's time is its log time
moved onto that clock by the median gap between the joint states' log times and stamps, so a
bag recorded on wall time of a robot stamping sim time (or the reverse) lines up. Every fault
is one BagError line naming the file and what is wrong: joint names the robot lacks, no joint
states, no commands for the robot's controllers, several robots' joint_states and no namespace.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from batchsim.controllers.topics import MessageKind
from batchsim.stamps import message_ns

JOINT_STATE = MessageKind.JOINT_STATE.value


class BagError(ValueError):
    """A bag that cannot be calibrated against: one line naming the file and the fault."""


@dataclasses.dataclass(frozen=True)
class Command:
    """One command message as the robot's controller received it.

    Attributes:
      time: seconds since the first joint state, when it arrived.
      topic: relative to the robot's namespace (`joint_trajectory_controller/joint_trajectory`).
      kind: FLOAT64_MULTI_ARRAY or JOINT_TRAJECTORY.
      data: a Float64MultiArray's values (width,); None for a trajectory.
      joint_names, point_times: a trajectory's joints and each point's time_from_start (npoint,).
      positions, velocities, accelerations: (npoint, len(joint_names)); the last two may be None.
      start: the trajectory's header stamp in seconds since the first joint state; 0: at once.
    """

    time: float
    topic: str
    kind: MessageKind
    data: np.ndarray | None = None
    joint_names: tuple[str, ...] = ()
    point_times: np.ndarray | None = None
    positions: np.ndarray | None = None
    velocities: np.ndarray | None = None
    accelerations: np.ndarray | None = None
    start: float = 0.0


@dataclasses.dataclass(frozen=True)
class RealBag:
    """The real robot's recording.

    Attributes:
      path: the file.
      namespace: the robot's namespace in the bag ("" at the root, else "/ns").
      joints: the joints its joint states name, in the order of the columns below.
      times: (nsample,) float64 seconds since the first joint state, non-decreasing.
      positions: (nsample, njoint) float64; velocities likewise, or None where none were recorded.
      commands: in arrival order.
      stamp0: the first joint state's stamp (s) on the bag's clock.
    """

    path: str
    namespace: str
    joints: tuple[str, ...]
    times: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray | None
    commands: tuple[Command, ...]
    stamp0: float

    @property
    def duration(self) -> float:
        return float(self.times[-1]) if len(self.times) else 0.0


def _seconds(stamp: Any) -> float:
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def _namespace(topic: str, suffix: str) -> str:
    return topic[: -len(suffix)].rstrip("/")


def read_bag(
    path: str | Path,
    joints: Sequence[str],
    inputs: Mapping[str, MessageKind],
    namespace: str | None = None,
    robot: str = "the robot",
) -> RealBag:
    """Read and check a rosbag2 MCAP.

    Args:
      joints: the robot's joint names.
      inputs: the robot's controllers' command topics (relative to a namespace) and their kinds.
      namespace: the robot's namespace in the bag ("/ns" or ""); None: the only one with joint_states.
      robot: the robot's name, for messages.
    """
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = Path(path)
    if not path.is_file():
        raise BagError(f"{path}: no such file")
    try:
        with path.open("rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            summary = reader.get_summary()
            if summary is None:
                raise BagError(f"{path}: an MCAP without a summary (was the recording finished?)")
            schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
            ns, commands = _topics(path, schemas, inputs, namespace)
            states, received = [], []
            wanted = [f"{ns}/joint_states", *commands]
            for _schema, channel, message, decoded in reader.iter_decoded_messages(topics=wanted):
                if channel.topic == wanted[0]:
                    states.append((int(message.log_time), decoded))
                else:
                    received.append((int(message.log_time), commands[channel.topic], decoded))
    except (McapError, OSError, ValueError) as e:
        if isinstance(e, BagError):
            raise
        raise BagError(f"{path}: not a readable MCAP: {e}") from None
    return _assemble(path, ns, joints, states, received, robot)


def _topics(
    path: Path, schemas: Mapping[str, str], inputs: Mapping[str, MessageKind], namespace: str | None
) -> tuple[str, dict[str, str]]:
    """The robot's namespace and its command topics in the bag: full topic -> relative topic."""
    found = sorted(_namespace(t, "joint_states") for t, s in schemas.items() if t.endswith("/joint_states") and s == JOINT_STATE)
    if namespace is not None:
        ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
        if ns not in found:
            have = ", ".join(f"{n}/joint_states" for n in found) or "none"
            raise BagError(f"{path}: no {ns}/joint_states (sensor_msgs/msg/JointState) in the bag (it has: {have})")
    elif not found:
        raise BagError(f"{path}: no joint_states (sensor_msgs/msg/JointState) in the bag: nothing to compare with")
    elif len(found) > 1:
        raise BagError(
            f"{path}: several robots' joint_states ({', '.join(n + '/joint_states' for n in found)}); "
            "name the robot's with --namespace"
        )
    else:
        ns = found[0]
    commands: dict[str, str] = {}
    for relative, kind in inputs.items():
        topic = f"{ns}/{relative}"
        if topic in schemas:
            if schemas[topic] != kind.value:
                raise BagError(f"{path}: {topic} carries {schemas[topic]}, its controller takes {kind.value}")
            commands[topic] = relative
    if not commands:
        expected = ", ".join(f"{ns}/{t} ({k.value})" for t, k in inputs.items()) or "none: the controllers take no commands"
        have = ", ".join(sorted(schemas)) or "nothing"
        raise BagError(f"{path}: no commands for the robot's controllers in the bag (expected {expected}; it has {have})")
    return ns, commands


def _assemble(
    path: Path,
    ns: str,
    joints: Sequence[str],
    states: list[tuple[int, Any]],
    received: list[tuple[int, str, Any]],
    robot: str,
) -> RealBag:
    if not states:
        raise BagError(f"{path}: {ns}/joint_states holds no message")
    named: list[str] = []
    for _, msg in states:
        for name in msg.name:
            if name not in named:
                named.append(name)
    unknown = [n for n in named if n not in joints]
    if unknown:
        raise BagError(
            f"{path}: {ns}/joint_states names joints {robot} lacks: {', '.join(unknown)} "
            f"(its joints: {', '.join(joints)})"
        )
    # integer nanoseconds until the first stamp is taken off: a float64 of 1.7e9 s keeps only 0.2 us
    stamps = np.array([message_ns(m.header.stamp) for _, m in states], np.int64)
    logs = np.array([t for t, _ in states], np.int64)
    if not stamps.any():  # a driver that leaves stamps unset: its log times are its clock
        stamps = logs.copy()
    order = np.argsort(stamps, kind="stable")
    offset = int(np.median(logs - stamps))  # log time - stamp
    first = int(stamps[order[0]])
    column = {n: k for k, n in enumerate(named)}
    n = len(states)
    positions = np.full((n, len(named)), np.nan)
    velocities = np.full((n, len(named)), np.nan)
    for row, k in enumerate(order):
        msg = states[k][1]
        cols = [column[name] for name in msg.name]
        if len(msg.position) == len(cols):
            positions[row, cols] = msg.position
        if len(msg.velocity) == len(cols):
            velocities[row, cols] = msg.velocity
    commands = [_command((t - offset - first) * 1e-9, relative, msg, first) for t, relative, msg in received]
    commands.sort(key=lambda c: c.time)
    return RealBag(
        str(path),
        ns,
        tuple(named),
        (stamps[order] - first) * 1e-9,
        positions,
        None if np.isnan(velocities).all() else velocities,
        tuple(commands),
        first * 1e-9,
    )


def _command(time: float, relative: str, msg: Any, first: int) -> Command:
    if hasattr(msg, "data"):
        return Command(time, relative, MessageKind.FLOAT64_MULTI_ARRAY, data=np.asarray(msg.data, np.float64))
    names = tuple(msg.joint_names)
    points = list(msg.points)

    def rows(field: str) -> np.ndarray | None:
        values = [getattr(p, field) for p in points]
        if not points or any(len(v) != len(names) for v in values):
            return None
        return np.asarray(values, np.float64).reshape(len(points), len(names))

    stamp = message_ns(msg.header.stamp)
    start = 0.0 if stamp == 0 else max((stamp - first) * 1e-9, 1e-9)  # 0 means "at once" to the controller
    return Command(
        time,
        relative,
        MessageKind.JOINT_TRAJECTORY,
        joint_names=names,
        point_times=np.array([_seconds(p.time_from_start) for p in points]),
        positions=rows("positions") if points else np.zeros((0, len(names))),
        velocities=rows("velocities"),
        accelerations=rows("accelerations"),
        start=start,
    )
