"""The messages of a robot's own state that every world publishes, as data: no rclpy here.

`<ns>/joint_states` (unless a joint_state_broadcaster publishes it), `<ns>/mujoco_actuators_states`
(mujoco_ros2_control's: the same joints' position, velocity and effort), `<ns>/sensors/<sensor>`
and the typed sensors per site (Imu, WrenchStamped), `<ns>/odom` for a floating base. In a world
of several robots (batchsim.fleet), each robot's under `<ns>/<robot>/`, named as it names them. Each is
an OutputSpec whose fields are columns of a channel: an (nworld, width) float64 array the
physics process fills (`fill(out)`) and copies into shared memory when a worker publishes it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Container, Sequence

import mujoco
import numpy as np

from batchsim.contract import Contract
from batchsim.model import RobotSpec, Sensor
from batchsim.parts.readings import actuator_state_index
from ros_bridge.naming import ros_names

JOINT_STATE = "sensor_msgs/msg/JointState"
#: fill(out (nworld, width)): a channel's values from host copies (what read() filled, a
#: controller's arrays), so the bridge may run it while the device steps (BridgeHost.while_stepping);
#: a fill that reads the engine itself (tf's body poses) is marked `fill.reads_engine = True`
ChannelFill = Callable[[np.ndarray], None]
#: channel(name, width, fill) -> the channel's index
Channel = Callable[[str, int, ChannelFill], int]


@dataclasses.dataclass(frozen=True)
class Field:
    """A named field of an output's message, filled from columns of a channel (-1: NaN)."""

    name: str
    channel: int
    columns: tuple[int, ...]


@dataclasses.dataclass(frozen=True)
class OutputSpec:
    """A message every world publishes on `<ns>/<topic>`.

    Attributes:
      topic: under the world's namespace.
      msg_type: "sensor_msgs/msg/JointState", ...
      fields: what fills the message (ros_bridge/worker/messages.py maps names onto message fields).
      names: JointState.name.
      frame_id, child_frame_id: "{ns}" is replaced by the world's namespace.
      covariance: (part, values) constants.
      every: control periods between two messages.
      on_request: the publisher is created only once a subscriber appears in the graph.
      state: the world's state: not published while the world is frozen (diverged), so a
        frozen world's stamps stop rather than look alive.
    """

    topic: str
    msg_type: str
    fields: tuple[Field, ...]
    names: tuple[str, ...] = ()
    frame_id: str = ""
    child_frame_id: str = ""
    covariance: tuple[tuple[str, tuple[float, ...]], ...] = ()
    every: int = 1
    on_request: bool = False
    state: bool = True

    @property
    def channels(self) -> frozenset[int]:
        return frozenset(f.channel for f in self.fields)


@dataclasses.dataclass(frozen=True)
class _Robot:
    """One robot's share of a world for its outputs: `prefix` before its topics (`arm_a/`, ""
    for a world of one robot), its joints, sensors and actuator joints by local name beside
    their world names, and the index of its floating base among `sim.base_states` (-1: none)."""

    prefix: str
    joints: tuple[tuple[str, str], ...]  # (local name, world name)
    sensors: tuple[str, ...]  # world names
    actuated: tuple[int, ...]  # entries of spec.actuator_joints
    base: int
    base_body: str  # world name


def _robots(spec: RobotSpec) -> list[_Robot]:
    if not spec.robots:
        return [
            _Robot(
                "",
                tuple((j.name, j.name) for j in spec.joints),
                tuple(s.name for s in spec.sensors),
                tuple(range(len(spec.actuator_joints))),
                0 if spec.floating_base is not None else -1,
                spec.floating_base.body if spec.floating_base is not None else "",
            )
        ]
    out, nbase = [], 0
    for r in spec.robots:
        base = -1
        if r.floating_base is not None:
            base, nbase = nbase, nbase + 1
        out.append(
            _Robot(
                r.prefix,
                tuple((r.local(j), j) for j in r.joints),
                r.sensors,
                tuple(k for k, (name, _, _) in enumerate(spec.actuator_joints) if name.startswith(r.prefix)),
                base,
                r.floating_base.body if r.floating_base is not None else "",
            )
        )
    return out


def robot_outputs(
    sim: Contract, channel: Channel, publish_every: int, sensor_every: int, *, replaced: Container[str] = ()
) -> list[OutputSpec]:
    """The outputs of `sim`'s joints, sensors and floating base: per robot of a world of several
    (`<robot>/joint_states`, ...), else the world's own; `replaced`: the robots' prefixes ("" for
    a world of one) whose joint_states a broadcaster publishes, so none is made here."""
    spec = sim.spec
    outputs: list[OutputSpec] = []
    robots = _robots(spec)
    column = {name: i for i, name in enumerate(spec.state_interfaces)}
    for r in robots:  # <ns>/<robot>/joint_states, unless a joint state broadcaster publishes it
        if not r.joints or r.prefix in replaced:
            continue
        gather = np.array(
            [column.get(f"{j}/{kind}", -1) for kind in ("position", "velocity", "effort") for _, j in r.joints],
            dtype=np.intp,
        )
        missing = gather < 0
        ch = channel(f"{r.prefix}joint_states", len(gather), _columns_of(lambda: sim.state, gather))
        nj = len(r.joints)
        fields = tuple(
            Field(kind, ch, tuple(range(k * nj, (k + 1) * nj)))
            for k, kind in enumerate(("position", "velocity", "effort"))
            if not missing[k * nj : (k + 1) * nj].all()
        )
        names = tuple(local for local, _ in r.joints)
        outputs.append(OutputSpec(f"{r.prefix}joint_states", JOINT_STATE, fields, names=names, every=publish_every))
    # <ns>/mujoco_actuators_states: mujoco_ros2_control's, every actuator's joint and every
    # joint no actuator drives, on the MuJoCo side of any transmission; on request
    index = actuator_state_index(spec)
    na_all = len(spec.actuator_joints)
    for r in robots:
        if not r.actuated:
            continue
        na = len(r.actuated)
        gather = np.concatenate([index[k * na_all + np.array(r.actuated)] for k in range(3)])
        names = tuple(spec.actuator_joints[k][0].removeprefix(r.prefix) for k in r.actuated)
        ch = channel(f"{r.prefix}mujoco_actuators_states", 3 * na, _columns_of(lambda: sim.actuator_states, gather))
        fields = tuple(Field(kind, ch, tuple(range(k * na, (k + 1) * na))) for k, kind in enumerate(("position", "velocity", "effort")))
        outputs.append(
            OutputSpec(
                f"{r.prefix}mujoco_actuators_states", JOINT_STATE, fields, names=names, every=publish_every, on_request=True
            )
        )
    # sensors/<sensor>, and typed sensors per site: created on request
    if spec.sensors:
        offsets = np.cumsum([0] + [s.dim for s in spec.sensors])
        sensors = list(spec.sensors)

        def fill_sensors(out: np.ndarray) -> None:
            data = sim.sensordata
            for s, lo, hi in zip(sensors, offsets[:-1], offsets[1:], strict=True):
                out[:, lo:hi] = data[s.name]

        ch = channel("sensordata", int(offsets[-1]), fill_sensors)
        at = {s.name: int(lo) for s, lo in zip(sensors, offsets[:-1], strict=True)}
        by_name = {s.name: s for s in sensors}
        for r in robots:
            outputs += _sensor_outputs(r, [by_name[n] for n in r.sensors], at, ch, publish_every, sensor_every)
    # <ns>/<robot>/odom: each floating base, its twist in the body frame
    for r in robots:
        if r.base < 0:
            continue
        ch = channel(f"{r.prefix}base", 13, _base_fill(sim, r.base))
        fields = (
            Field("position", ch, (0, 1, 2)),
            Field("orientation", ch, (4, 5, 6, 3)),
            Field("linear", ch, (7, 8, 9)),
            Field("angular", ch, (10, 11, 12)),
        )
        outputs.append(
            OutputSpec(
                # the pose is in the world's root frame: `odom` for a world of one floating-base robot
                # (REP 105), `world` for a world of several (batchsim.model.frames)
                f"{r.prefix}odom", "nav_msgs/msg/Odometry", fields, frame_id="{ns}/world" if r.prefix else "{ns}/odom",
                child_frame_id=f"{{ns}}/{r.base_body}", every=publish_every,
            )
        )  # fmt: skip
    return outputs


def _base_fill(sim: Contract, k: int) -> ChannelFill:
    def fill_base(out: np.ndarray) -> None:
        base = sim.base_states[:, k]  # pose, world-frame linear and body-frame angular velocity
        out[:, 0:7] = base[:, 0:7]
        out[:, 7:10] = rotate_inverse(base[:, 3:7], base[:, 7:10])
        out[:, 10:13] = base[:, 10:13]

    return fill_base


def _sensor_outputs(
    r: _Robot, sensors: list[Sensor], at: dict[str, int], ch: int, publish_every: int, sensor_every: int
) -> list[OutputSpec]:
    """A robot's `sensors/<sensor>` topics, and its sites' Imu and WrenchStamped."""
    outputs = []
    local = [s.name.removeprefix(r.prefix) for s in sensors]
    for s, token in zip(sensors, ros_names(local), strict=True):
        cols = tuple(range(at[s.name], at[s.name] + s.dim))
        kind = "std_msgs/msg/Float64" if s.dim == 1 else "std_msgs/msg/Float64MultiArray"
        outputs.append(
            OutputSpec(f"{r.prefix}sensors/{token}", kind, (Field("data", ch, cols),), every=sensor_every, on_request=True)
        )
    T = mujoco.mjtSensor
    parts = (T.mjSENS_FRAMEQUAT, T.mjSENS_GYRO, T.mjSENS_ACCELEROMETER, T.mjSENS_FORCE, T.mjSENS_TORQUE)
    by_site: dict[str, dict[mujoco.mjtSensor, str]] = {}  # a site's IMU and wrench are made of these
    for s in sensors:
        if s.objname and s.type in parts:
            by_site.setdefault(s.objname, {}).setdefault(s.type, s.name)
    for site, kinds in by_site.items():
        token = ros_names([site.removeprefix(r.prefix)])[0]

        def cols(name: str, order: Sequence[int]) -> tuple[int, ...]:
            return tuple(at[name] + k for k in order)

        frame = f"{{ns}}/{site}"  # the site's world name: `arm_a/wrist` in a fleet's world
        if T.mjSENS_GYRO in kinds and T.mjSENS_ACCELEROMETER in kinds:
            fields = [
                Field("angular_velocity", ch, cols(kinds[T.mjSENS_GYRO], (0, 1, 2))),
                Field("linear_acceleration", ch, cols(kinds[T.mjSENS_ACCELEROMETER], (0, 1, 2))),
            ]
            covariance: tuple[tuple[str, tuple[float, ...]], ...] = ()
            if T.mjSENS_FRAMEQUAT in kinds:  # MuJoCo (w, x, y, z) -> ROS (x, y, z, w)
                fields.insert(0, Field("orientation", ch, cols(kinds[T.mjSENS_FRAMEQUAT], (1, 2, 3, 0))))
            else:  # REP 145: no orientation estimate
                covariance = (("orientation", (-1.0,) + (0.0,) * 8),)
            outputs.append(
                OutputSpec(
                    f"{r.prefix}sensors/{token}/imu", "sensor_msgs/msg/Imu", tuple(fields), frame_id=frame,
                    covariance=covariance, every=publish_every, on_request=True,
                )
            )  # fmt: skip
        if T.mjSENS_FORCE in kinds and T.mjSENS_TORQUE in kinds:
            fields = [
                Field("force", ch, cols(kinds[T.mjSENS_FORCE], (0, 1, 2))),
                Field("torque", ch, cols(kinds[T.mjSENS_TORQUE], (0, 1, 2))),
            ]
            outputs.append(
                OutputSpec(
                    f"{r.prefix}sensors/{token}/wrench", "geometry_msgs/msg/WrenchStamped", tuple(fields),
                    frame_id=frame, every=publish_every, on_request=True,
                )
            )  # fmt: skip
    return outputs


def _columns_of(source: Callable[[], np.ndarray], gather: np.ndarray) -> Callable[[np.ndarray], None]:
    """A channel's fill: columns `gather` of `source()` (nworld, n); -1 fills NaN. A function
    of its own, so each fill keeps its own indices (closures in one scope share names)."""
    missing = gather < 0
    src = np.maximum(gather, 0)

    def fill(out: np.ndarray) -> None:
        out[...] = source()[:, src]  # fancy indexing: 2.2x faster than np.take(axis=1, out=) on (1024, 36) rows
        if missing.any():
            out[:, missing] = np.nan

    return fill


def rotate_inverse(quat: np.ndarray, vec: np.ndarray) -> np.ndarray:
    """Rotate (n, 3) world vectors into the frames of (n, 4) unit quaternions (w, x, y, z)."""
    w = quat[:, :1]
    u = -quat[:, 1:4]  # the conjugate rotates world -> body
    t = 2.0 * np.cross(u, vec)
    return vec + w * t + np.cross(u, t)
