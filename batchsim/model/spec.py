"""What batchsim knows of a robot: the compiled model and the interfaces it exposes, as data."""

from __future__ import annotations

import dataclasses
import enum
from pathlib import Path

import mujoco
import numpy as np

from batchsim.sensors.mjcf import SensorDeclarations

ROS2_PLUGIN = "mujoco.ros2"
ROS2_PLUGIN_KEYS = ("ros_namespace", "topic_queue_size", "topic_reliability")


class ModelError(ValueError):
    """A model that cannot be loaded: the message is one line naming the file and cause."""


class InterfaceKind(enum.Enum):
    """ros2_control's standard joint interface types (hardware_interface/types)."""

    POSITION = "position"
    VELOCITY = "velocity"
    EFFORT = "effort"


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

    name: str  # "<joint>/<kind>" or "<actuator>/<kind>"
    kind: InterfaceKind
    actuator: str
    actuator_id: int
    joint: str | None


@dataclasses.dataclass(frozen=True)
class Sensor:
    """An MJCF sensor: its slice of `sensordata` and its field names."""

    name: str
    type: str  # MuJoCo's sensor type, lower case without prefix: "force", "framequat"
    adr: int
    dim: int
    fields: tuple[str, ...]
    objname: str | None  # the site, joint, actuator or frame object it is attached to


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
    source: str  # "qpos", "qvel", "qfrc_actuator" or "sensordata"
    index: int


@dataclasses.dataclass
class InitialState:
    """The state every world starts in and `reset()` returns to: MuJoCo's state components
    (mjSTATE_INTEGRATION) as an MjData holds them, each in model order.

    By default the model's own (`qpos0`, zero velocities); a ros2_control `initial_value`
    overrides a joint's qpos, and `qpos0` itself is never changed: it is the joints'
    kinematic zero, not where they start.
    """

    time: float
    qpos: np.ndarray  # (nq,)
    qvel: np.ndarray  # (nv,)
    act: np.ndarray  # (na,)
    ctrl: np.ndarray  # (nu,)
    mocap_pos: np.ndarray  # (nmocap, 3)
    mocap_quat: np.ndarray  # (nmocap, 4)
    source: str = "qpos0"  # what it was taken from, for `batchsim info` and messages

    @classmethod
    def of_model(cls, m: mujoco.MjModel) -> InitialState:
        """The model's defaults, as mj_resetData leaves an MjData."""
        d = mujoco.MjData(m)
        return cls.of_data(d, "qpos0")

    @classmethod
    def of_data(cls, d: mujoco.MjData, source: str) -> InitialState:
        return cls(
            time=float(d.time),
            qpos=d.qpos.copy(),
            qvel=d.qvel.copy(),
            act=d.act.copy(),
            ctrl=d.ctrl.copy(),
            mocap_pos=d.mocap_pos.copy(),
            mocap_quat=d.mocap_quat.copy(),
            source=source,
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


@dataclasses.dataclass
class RobotSpec:
    """A compiled model and the interfaces batchsim exposes of it.

    Attributes:
      name: the model's name (the MJCF's `model` attribute, else the file stem).
      path: the MJCF file, or None for a model given as an XML string.
      mjmodel: the compiled model.
      xml: the MJCF that was compiled, with the extension and ros2_control blocks removed.
      joints: the exposed 1-DOF joints, in model order.
      state: one entry per state interface, in `export_state_interfaces()` order.
      commands: one entry per command interface, in `export_command_interfaces()` order.
      sensors: every exposed MJCF sensor, in model order.
      ros: the `mujoco.ros2` extension block's config, if the MJCF has one.
      floating_base: the free joint of the robot's own tree (see `floating_base`), or None.
      initial: the state every world starts in and `reset` returns to.
      problems: configuration errors found in a ros2_control block; `on_configure` reports them.
      sensor_declarations: lidars the MJCF and ros2_control file declare outside MuJoCo's own
        sensors (`<lidar>` elements, mujoco.plugin.lidar sensors; see batchsim.sensors.mjcf).
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
    problems: list[str] = dataclasses.field(default_factory=list)
    sensor_declarations: SensorDeclarations = dataclasses.field(default_factory=SensorDeclarations)

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
