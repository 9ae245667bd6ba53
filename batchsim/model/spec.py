"""What batchsim knows of a robot: the compiled model and the interfaces it exposes, as data."""

from __future__ import annotations

import dataclasses
import enum
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from batchsim.model.lidars import SensorDeclarations
from batchsim.pid import PidGains
from batchsim.types import StateSource

ROS2_PLUGIN = "mujoco.ros2"
ROS2_PLUGIN_KEYS = ("ros_namespace", "topic_queue_size", "topic_reliability")


class ModelError(ValueError):
    """A model that cannot be loaded: the message is one line naming the file and cause."""


class InterfaceKind(enum.Enum):
    """ros2_control's standard joint interface types (hardware_interface/types)."""

    POSITION = "position"
    VELOCITY = "velocity"
    EFFORT = "effort"

    @classmethod
    def of_name(cls, name: str) -> InterfaceKind | None:
        """An interface name's kind: `torque` and `force` are names of the effort interface."""
        name = EFFORT_ALIASES.get(name, name)
        return next((k for k in cls if k.value == name), None)


# names ros2_control (and mujoco_ros2_control) give the effort interface
EFFORT_ALIASES = {"torque": "effort", "force": "effort"}


class CommandMode(enum.Enum):
    """How a command interface's value becomes its actuator's `ctrl`."""

    DIRECT = "direct"  # ctrl = scale * command + offset (scale 1, offset 0 unless a gripper is scaled)
    POSITION_PID = "position_pid"  # ctrl = PID(command - qpos of the joint)
    VELOCITY_PID = "velocity_pid"  # ctrl = PID(command - qvel of the joint)
    TRANSMITTED = "transmitted"  # through a transmission onto `RobotSpec.actuator_commands`


class TransmissionKind(enum.Enum):
    """The transmissions of ros2_control's transmission_interface batchsim runs."""

    SIMPLE = "transmission_interface/SimpleTransmission"
    DIFFERENTIAL = "transmission_interface/DifferentialTransmission"


@dataclasses.dataclass(frozen=True)
class Transmission:
    """A ros2_control transmission: joints on one side, actuators on the other, related
    linearly as transmission_interface relates them:

        actuator position = matrix @ (joint position - offset)
        actuator velocity = matrix @ joint velocity
        joint effort      = matrix.T @ actuator effort

    An actuator is named as mujoco_ros2_control names them: a MuJoCo joint driven by an
    actuator, or an actuator's own name. `joints[k]` and `actuators[k]` are paired: a
    joint's state is gathered where its actuator's is, then mapped (batchsim.parts.transmissions).
    """

    name: str
    kind: TransmissionKind
    joints: tuple[str, ...]
    actuators: tuple[str, ...]
    matrix: tuple[tuple[float, ...], ...]  # (nactuator, njoint)
    offset: tuple[float, ...]  # per joint

    def actuator_from_joint(self, kind: InterfaceKind) -> tuple[np.ndarray, np.ndarray]:
        """(A, b) with actuator values = A @ joint values + b, for commands of `kind`."""
        m = np.array(self.matrix)
        if kind is InterfaceKind.EFFORT:
            return np.linalg.inv(m).T, np.zeros(len(m))
        return m, (-m @ np.array(self.offset) if kind is InterfaceKind.POSITION else np.zeros(len(m)))

    def joint_from_actuator(self, kind: InterfaceKind) -> tuple[np.ndarray, np.ndarray]:
        """(A, b) with joint values = A @ actuator values + b, for states of `kind`."""
        m = np.array(self.matrix)
        if kind is InterfaceKind.EFFORT:
            return m.T, np.zeros(len(m))
        return np.linalg.inv(m), (np.array(self.offset) if kind is InterfaceKind.POSITION else np.zeros(len(m)))


@dataclasses.dataclass(frozen=True)
class Joint:
    """A 1-DOF (hinge or slide) joint: where its position and velocity live."""

    name: str
    id: int
    qposadr: int
    dofadr: int


@dataclasses.dataclass(frozen=True)
class CommandInterface:
    """One command interface and the actuator (`ctrl` column) that serves it."""

    name: str  # "<joint>/<kind>" or "<actuator>/<kind>" (kind as the block names it: effort, torque)
    kind: InterfaceKind
    actuator: str
    actuator_id: int
    joint: str | None
    mode: CommandMode = CommandMode.DIRECT
    scale: float = 1.0  # DIRECT: ctrl = scale * command + offset
    offset: float = 0.0
    pid: PidGains | None = None  # the PID modes: the gains
    qposadr: int = -1  # the PID modes: where the joint's position / velocity are measured
    dofadr: int = -1


@dataclasses.dataclass(frozen=True)
class MimicCommand:
    """A mimic joint's actuator, driven from the mimicked joint's command interface:
    ctrl[actuator_id] = multiplier * command[source] + offset."""

    joint: str
    source: str  # the mimicked joint's command interface
    actuator: str
    actuator_id: int
    multiplier: float
    offset: float


@dataclasses.dataclass(frozen=True)
class Sensor:
    """An MJCF sensor: its slice of `sensordata` and its field names."""

    name: str
    type: mujoco.mjtSensor  # compare with ==: a pybind11 enum, a new object once unpickled
    adr: int
    dim: int
    fields: tuple[str, ...]
    objname: str | None  # the site, joint, actuator or frame object it is attached to

    @property
    def type_name(self) -> str:
        """The type as `batchsim info` shows it: lower case without prefix ("force", "framequat")."""
        return self.type.name.removeprefix("mjSENS_").lower()


@dataclasses.dataclass(frozen=True)
class RosPluginConfig:
    """The config keys of an MJCF `mujoco.ros2` extension block."""

    instance: str
    ros_namespace: str = ""
    topic_queue_size: int = 10
    topic_reliability: str = "reliable"


@dataclasses.dataclass(frozen=True)
class FloatingBase:
    """The free joint of the robot's own tree: where its pose and twist live in qpos / qvel."""

    joint: str
    body: str
    qposadr: int  # qpos[qposadr : qposadr + 7]: position (3), orientation quaternion (w, x, y, z)
    dofadr: int  # qvel[dofadr : dofadr + 6]: linear velocity (world frame), angular velocity (body frame)


@dataclasses.dataclass(frozen=True)
class StateColumn:
    """Where one state interface's value comes from: a field and an index into it."""

    name: str
    source: StateSource
    index: int
    sign: float = 1.0  # -1: read negated (mujoco_ros2_control's force/torque sensors)


@dataclasses.dataclass
class InitialState:
    """The state every world starts in and `reset()` returns to: MuJoCo's state components
    (mjSTATE_INTEGRATION) as an MjData holds them, each in model order.

    A keyframe (`home` by default, when the model has one), else the model's own (`qpos0`,
    zero velocities); a ros2_control `initial_value` overrides a joint's qpos (unless the
    keyframe was asked for by name), and `qpos0` itself is never changed: it is the joints'
    kinematic zero, not where they start.
    """

    time: float
    qpos: np.ndarray  # (nq,)
    qvel: np.ndarray  # (nv,)
    act: np.ndarray  # (na,)
    ctrl: np.ndarray  # (nu,)
    mocap_pos: np.ndarray  # (nmocap, 3)
    mocap_quat: np.ndarray  # (nmocap, 4)
    keyframe: str | None = None  # the keyframe's name (or "#<index>" for an unnamed one); None: qpos0
    # the keyframe gives ctrl: the initial command holds it; a world of several robots
    # (batchsim.fleet) says it per actuator, (nu,) bool, as each robot's own keyframe does
    ctrl_given: bool | np.ndarray = False
    initial_values: bool = False  # ros2_control initial_value set some joints' qpos
    # a world of several robots (batchsim.fleet): what each robot's start was taken from
    label: str | None = None

    def gives_ctrl(self, actuator: int) -> bool:
        """Whether the keyframe gives actuator `actuator`'s ctrl (then its command starts there)."""
        if isinstance(self.ctrl_given, np.ndarray):
            return bool(self.ctrl_given[actuator])
        return bool(self.ctrl_given)

    @property
    def is_qpos0(self) -> bool:
        """The model's own defaults, as mj_resetData leaves an MjData: no keyframe, no initial_value."""
        return self.keyframe is None and not self.initial_values and self.label is None

    @property
    def source(self) -> str:
        """What it was taken from, for `batchsim info` and messages: `qpos0` or `keyframe 'home'`,
        then ` with ros2_control initial_value` where those were applied; per robot in a fleet's world."""
        if self.label is not None:
            return self.label
        taken = "qpos0" if self.keyframe is None else f"keyframe {self.keyframe}"
        return taken + (" with ros2_control initial_value" if self.initial_values else "")

    @classmethod
    def of_model(cls, m: mujoco.MjModel) -> InitialState:
        """The model's defaults, as mj_resetData leaves an MjData."""
        d = mujoco.MjData(m)
        return cls.of_data(d)

    @classmethod
    def of_keyframe(cls, m: mujoco.MjModel, key: int, label: str, ctrl_given: bool) -> InitialState:
        """Keyframe `key`, as mj_resetDataKeyframe leaves an MjData."""
        d = mujoco.MjData(m)
        mujoco.mj_resetDataKeyframe(m, d, key)
        state = cls.of_data(d)
        state.keyframe = label
        state.ctrl_given = ctrl_given
        return state

    @classmethod
    def of_data(cls, d: mujoco.MjData) -> InitialState:
        return cls(
            time=float(d.time),
            qpos=d.qpos.copy(),
            qvel=d.qvel.copy(),
            act=d.act.copy(),
            ctrl=d.ctrl.copy(),
            mocap_pos=d.mocap_pos.copy(),
            mocap_quat=d.mocap_quat.copy(),
        )

    def apply(self, m: mujoco.MjModel, d: mujoco.MjData) -> None:
        """Reset `d` to this state and run mj_forward, so derived fields match it."""
        mujoco.mj_resetData(m, d)
        d.time = self.time
        d.qpos[:] = self.qpos
        d.qvel[:] = self.qvel
        d.act[:] = self.act
        d.ctrl[:] = self.ctrl
        d.mocap_pos[:] = self.mocap_pos
        d.mocap_quat[:] = self.mocap_quat
        mujoco.mj_forward(m, d)


@dataclasses.dataclass(frozen=True)
class RobotPart:
    """One robot of a world that holds several (batchsim.fleet): which of the world's interfaces,
    sensors, joints and bodies are its own, as ros2_control exports one hardware component.

    Every name in the world's RobotSpec is prefixed `<robot>/` (MjSpec attach's prefix), so two
    copies of one model are two robots; `local` strips it again for the robot's own namespace.

    Attributes:
      name: the robot's name, its namespace inside the world (`/world_3/<name>/...`).
      model: what it was loaded from (a shipped name or a file), for messages and `info`.
      state: (nstate_r,) int64, its columns of the world's `state`, in its own order.
      commands: (ncommand_r,) int64, its columns of the world's `command`.
      sensors: its MJCF sensors' names in the world's spec (prefixed).
      joints: its 1-DOF joints' names in the world's spec (prefixed).
      bodies: (first, count): its bodies are `first .. first + count - 1` of the world's model.
      qpos, dofs, actuators: (first, count) likewise: its block of the world's qpos, of qvel
        (and qfrc_*), and of its actuators (ctrl): what a reset of this robot alone restores.
      floating_base: its own free joint, or None for a fixed base.
      pose: (x, y, z, yaw) where it was placed in the world.
      controllers: its controller_manager YAML, or None (the model's default).
      sensor_config: its sensors/plugins YAML, or None.
      sensor_settings: that file read, checked against the robot alone and named as the world
        names it (batchsim.fleet.sensors), or None.
      spec: the robot loaded alone (unprefixed names, its own model): what its description says.
    """

    name: str
    model: str
    state: np.ndarray
    commands: np.ndarray
    sensors: tuple[str, ...]
    joints: tuple[str, ...]
    bodies: tuple[int, int]
    qpos: tuple[int, int]
    dofs: tuple[int, int]
    actuators: tuple[int, int]
    floating_base: FloatingBase | None
    pose: tuple[float, float, float, float]
    controllers: Path | None = None
    sensor_config: Path | None = None
    sensor_settings: Any = None  # a batchsim.sensors.SensorConfig: the model is a floor below the sensors
    spec: RobotSpec | None = None

    @property
    def prefix(self) -> str:
        """What its names carry in the world's spec: `<name>/`."""
        return f"{self.name}/"

    def local(self, name: str) -> str:
        """A world name of this robot's (`arm_a/joint1/position`) as the robot alone names it."""
        return name.removeprefix(self.prefix)


@dataclasses.dataclass
class RobotSpec:
    """A compiled model and the interfaces batchsim exposes of it.

    Attributes:
      name: the model's name (the MJCF's `model` attribute, else the file stem).
      path: the MJCF file (or the URDF an MJCF was generated from), or None for a model given as an XML string.
      mjmodel: the compiled model.
      xml: the MJCF that was compiled, with the extension and ros2_control blocks removed.
      joints: the exposed 1-DOF joints, in model order.
      state: one entry per state interface, in `export_state_interfaces()` order.
      commands: one entry per command interface, in `export_command_interfaces()` order.
      sensors: every exposed MJCF sensor, in model order.
      ros: the `mujoco.ros2` extension block's config, if the MJCF has one.
      floating_base: the free joint of the robot's own tree (see `floating_base`), or None.
      initial: the state every world starts in and `reset` returns to.
      keyframes: the model's keyframe names, in model order ("" for an unnamed one).
      mimics: mimic joints driven from the joint they mimic.
      problems: configuration errors found in a ros2_control block; `on_configure` reports them.
      sensor_declarations: lidars the MJCF and ros2_control file declare outside MuJoCo's own
        sensors (`<lidar>` elements, mujoco.plugin.lidar sensors; see batchsim.model.lidars).
      warnings: what batchsim does not act on (an unknown param, a plugin): one line each.
      transmissions: ros2_control transmissions; their joints' commands are TRANSMITTED.
      actuator_commands: what drives ctrl where transmissions stand between: `commands`
        with each TRANSMITTED interface replaced by its actuators' (`<actuator>/<interface>`);
        None without transmissions (then `commands` drive ctrl).
      actuator_joints: the joints mujoco_ros2_control reports on `mujoco_actuators_states`:
        each actuator's (under its joint's name, or its own for a tendon or site), then the
        hinge and slide joints no actuator drives, as (name, qposadr, dofadr); an actuator
        with no joint of its name has addresses -1.
      robots: the robots of a world composed from a fleet file (batchsim.fleet), in the order
        their interfaces appear; empty for a model that is one robot.
      placements: robots a fleet file places at random per world (batchsim.variation.Placement):
        `batchsim.make` adds them to the worlds' variation.
      sensor_config: the cameras, lidars, noise and plugins a fleet's robots' own sensors files
        ask for, merged and named as the world names them (batchsim.fleet.sensors), or None:
        `batchsim.make` applies it, with a `sensors=` given for the whole fleet laid over it.
    """

    name: str
    path: Path | None
    mjmodel: mujoco.MjModel
    xml: str
    joints: list[Joint]
    state: list[StateColumn]
    commands: list[CommandInterface]
    sensors: list[Sensor]
    ros: RosPluginConfig | None = None
    floating_base: FloatingBase | None = None
    initial: InitialState | None = None
    keyframes: list[str] = dataclasses.field(default_factory=list)
    mimics: list[MimicCommand] = dataclasses.field(default_factory=list)
    problems: list[str] = dataclasses.field(default_factory=list)
    sensor_declarations: SensorDeclarations = dataclasses.field(default_factory=SensorDeclarations)
    warnings: list[str] = dataclasses.field(default_factory=list)
    transmissions: list[Transmission] = dataclasses.field(default_factory=list)
    actuator_commands: list[CommandInterface] | None = None
    actuator_joints: list[tuple[str, int, int]] = dataclasses.field(default_factory=list)
    robots: list[RobotPart] = dataclasses.field(default_factory=list)
    placements: tuple = ()  # of batchsim.variation.Placement
    sensor_config: Any = None  # a batchsim.sensors.SensorConfig: the model is a floor below the sensors

    @property
    def floating_bases(self) -> list[FloatingBase]:
        """Every floating base read(): the model's own, or each robot's of a fleet's world, in order."""
        if self.floating_base is not None:
            return [self.floating_base]
        return [r.floating_base for r in self.robots if r.floating_base is not None]

    def robot(self, name: str) -> RobotPart:
        """The robot of that name (a world of several, batchsim.fleet); KeyError naming the robots."""
        for r in self.robots:
            if r.name == name:
                return r
        known = ", ".join(r.name for r in self.robots) or "none: the model is one robot"
        raise KeyError(f"no robot named {name!r}; robots: {known}")

    @property
    def state_interfaces(self) -> list[str]:
        return [c.name for c in self.state]

    @property
    def command_interfaces(self) -> list[str]:
        return [c.name for c in self.commands]

    def sensor(self, name: str) -> Sensor:
        for s in self.sensors:
            if s.name == name:
                return s
        raise KeyError(f"no sensor named {name!r}; sensors: {', '.join(s.name for s in self.sensors)}")
