"""MJCF loading, the extension-block config, and interface discovery.

`load(model)` turns a model name from `models/` or a path to an MJCF file into a
`RobotSpec`: the compiled `mujoco.MjModel` plus everything batchsim exposes of it, named
the way ros2_control names things:

- every hinge or slide joint gets the state interfaces `<joint>/position`, `/velocity`
  and `/effort`;
- every actuator gets a command interface by its type, as ros2_control users expect: a
  `motor` is `effort`, a `position` actuator is `position`, a `velocity` (or
  `intvelocity`) actuator is `velocity`; it is named after its joint
  (`joint1/position`) when it drives one, else after itself;
- every sensor is exposed with ros2_control-style field names (`wrist_force/force.x`).

Two XML blocks that MuJoCo itself does not know are read and removed before compiling:

- `<extension><plugin plugin="mujoco.ros2">`, written for the `mujoco.ros2` MuJoCo
  plugin: its config keys (`ros_namespace`, `topic_queue_size`, `topic_reliability`) are
  kept in `RobotSpec.ros`;
- `<ros2_control>`, the block a real robot's URDF carries (inline in the MJCF, or given
  as a file or XML string through `ros2_control=`): it narrows which joints, interfaces
  and sensors are exposed. Problems with it (a joint the model lacks, a command interface
  no actuator serves) are collected in `RobotSpec.problems` and reported by
  `on_configure`, as a hardware component reports them in ros2_control.
"""

from __future__ import annotations

import dataclasses
import enum
import importlib.resources
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np

ROS2_PLUGIN = "mujoco.ros2"
ROS2_PLUGIN_KEYS = ("ros_namespace", "topic_queue_size", "topic_reliability")


class ModelError(ValueError):
    """A model that cannot be loaded: the message is one line naming the file and cause."""


class InterfaceKind(enum.Enum):
    """ros2_control's standard joint interface types (hardware_interface/types)."""

    POSITION = "position"
    VELOCITY = "velocity"
    EFFORT = "effort"


# Field names of each MuJoCo sensor type's components, ros2_control style.
_XYZ = ("x", "y", "z")
_WXYZ = ("w", "x", "y", "z")
_SENSOR_FIELDS: dict[str, tuple[str, tuple[str, ...]]] = {
    "touch": ("force", ()),
    "accelerometer": ("linear_acceleration", _XYZ),
    "velocimeter": ("linear_velocity", _XYZ),
    "gyro": ("angular_velocity", _XYZ),
    "force": ("force", _XYZ),
    "torque": ("torque", _XYZ),
    "magnetometer": ("magnetic_field", _XYZ),
    "rangefinder": ("range", ()),
    "jointpos": ("position", ()),
    "jointvel": ("velocity", ()),
    "tendonpos": ("position", ()),
    "tendonvel": ("velocity", ()),
    "actuatorpos": ("position", ()),
    "actuatorvel": ("velocity", ()),
    "actuatorfrc": ("effort", ()),
    "jointactfrc": ("effort", ()),
    "tendonactfrc": ("effort", ()),
    "ballquat": ("orientation", _WXYZ),
    "ballangvel": ("angular_velocity", _XYZ),
    "framepos": ("position", _XYZ),
    "framequat": ("orientation", _WXYZ),
    "framexaxis": ("x_axis", _XYZ),
    "frameyaxis": ("y_axis", _XYZ),
    "framezaxis": ("z_axis", _XYZ),
    "framelinvel": ("linear_velocity", _XYZ),
    "frameangvel": ("angular_velocity", _XYZ),
    "framelinacc": ("linear_acceleration", _XYZ),
    "frameangacc": ("angular_acceleration", _XYZ),
    "subtreecom": ("position", _XYZ),
    "subtreelinvel": ("linear_velocity", _XYZ),
    "subtreeangmom": ("angular_momentum", _XYZ),
    "clock": ("time", ()),
}


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
      problems: configuration errors found in a ros2_control block; `on_configure` reports them.
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
    problems: list[str] = dataclasses.field(default_factory=list)

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


def _models_root():
    """The shipped models: the `batchsim.models` package once installed, else the checkout's models/."""
    try:
        return importlib.resources.files("batchsim.models")
    except ModuleNotFoundError:  # a source checkout on PYTHONPATH, not installed
        return Path(__file__).resolve().parent.parent / "models"


def model_names() -> list[str]:
    """The robots shipped with batchsim, loadable by name."""
    root = _models_root()
    return sorted(p.name[:-4] for p in root.iterdir() if p.name.endswith(".xml"))


def model_path(name: str) -> Path:
    """The MJCF file of a shipped model, or of a path; ModelError if neither exists."""
    path = Path(name).expanduser()
    if path.suffix.lower() in (".xml", ".mjcf") or path.exists():
        if not path.is_file():
            raise ModelError(f"{name}: no such file")
        return path
    shipped = _models_root() / f"{name}.xml"
    if not shipped.is_file():
        raise ModelError(
            f"unknown model {name!r}: not a file and not one of the shipped models "
            f"({', '.join(model_names())})"
        )
    return Path(str(shipped))


def load(model: str | Path, *, ros2_control: str | Path | None = None) -> RobotSpec:
    """Load a shipped model by name or an MJCF file by path into a RobotSpec.

    Args:
      model: a name from `models/` ("arm", "car", "quadruped") or a path to an MJCF file.
      ros2_control: a ros2_control block narrowing the exposed interfaces: a path to a
        URDF/XML file that contains one, or the XML text itself. An inline
        `<ros2_control>` in the MJCF is used when this is None.

    Raises:
      ModelError: a missing file, malformed XML, or a model MuJoCo rejects; one line.
    """
    path = model_path(str(model))
    try:
        text = path.read_text()
    except OSError as e:
        raise ModelError(f"{path}: {e.strerror}") from None
    return load_string(text, path=path, ros2_control=ros2_control)


def load_string(
    text: str, *, path: Path | None = None, ros2_control: str | Path | None = None
) -> RobotSpec:
    """Load an MJCF given as text; `path`, if given, names it and anchors relative assets."""
    where = str(path) if path else "<string>"
    try:
        root = ET.fromstring(text)
    except ET.ParseError as e:
        line, col = e.position
        raise ModelError(f"{where}:{line}:{col}: malformed XML: {_parse_reason(e)}") from None
    if root.tag != "mujoco":
        raise ModelError(f"{where}: not an MJCF file (root element <{root.tag}>, expected <mujoco>)")

    ros = _take_ros_plugin(root, where)
    inline_block = _take_element(root, "ros2_control")
    stripped = ros is not None or inline_block is not None
    if stripped and path is not None:
        _anchor_relative_files(root, path.parent)
    xml = ET.tostring(root, encoding="unicode") if stripped else text

    try:
        if stripped or path is None:
            mjmodel = mujoco.MjModel.from_xml_string(xml)
        else:
            mjmodel = mujoco.MjModel.from_xml_path(str(path))
    except ValueError as e:
        raise ModelError(f"{where}: {_one_line(str(e))}") from None

    block = inline_block
    if ros2_control is not None:
        block = _ros2_control_block(ros2_control)
    name = root.get("model") or (path.stem if path else "model")
    return _discover(name, path, mjmodel, xml, ros, block)


def _parse_reason(e: ET.ParseError) -> str:
    # "mismatched tag: line 3, column 2" -> "mismatched tag"
    return re.sub(r":? line \d+, column \d+$", "", str(e))


def _one_line(message: str) -> str:
    """MuJoCo's multi-line compile error as one line: 'XML Error: ... (Element 'x', line 5)'."""
    parts = [p.strip() for p in message.strip().splitlines() if p.strip()]
    if not parts:
        return "MuJoCo could not compile the model"
    head, rest = parts[0], parts[1:]
    return head + (f" ({'; '.join(rest)})" if rest else "")


def _take_element(root: ET.Element, tag: str) -> ET.Element | None:
    """Remove and return the first `tag` element anywhere under root."""
    for parent in root.iter():
        for child in list(parent):
            if child.tag == tag:
                parent.remove(child)
                return child
    return None


def _take_ros_plugin(root: ET.Element, where: str) -> RosPluginConfig | None:
    """Remove the `mujoco.ros2` extension plugin and return its config keys."""
    config = None
    for extension in root.findall("extension"):
        for plugin in extension.findall("plugin"):
            if plugin.get("plugin") != ROS2_PLUGIN:
                continue
            extension.remove(plugin)
            instance = plugin.find("instance")
            keys: dict[str, str] = {}
            if instance is not None:
                for c in instance.findall("config"):
                    keys[c.get("key", "")] = c.get("value", "")
            unknown = sorted(set(keys) - set(ROS2_PLUGIN_KEYS))
            if unknown:
                raise ModelError(
                    f"{where}: unknown {ROS2_PLUGIN} config key {unknown[0]!r} "
                    f"(known: {', '.join(ROS2_PLUGIN_KEYS)})"
                )
            try:
                depth = int(keys.get("topic_queue_size", 10))
            except ValueError:
                raise ModelError(
                    f"{where}: {ROS2_PLUGIN} topic_queue_size must be an integer, "
                    f"got {keys['topic_queue_size']!r}"
                ) from None
            reliability = keys.get("topic_reliability", "reliable").lower()
            if reliability not in ("reliable", "best_effort"):
                raise ModelError(
                    f"{where}: {ROS2_PLUGIN} topic_reliability must be reliable or "
                    f"best_effort, got {reliability!r}"
                )
            config = RosPluginConfig(
                instance=instance.get("name", "") if instance is not None else "",
                ros_namespace=keys.get("ros_namespace", ""),
                topic_queue_size=depth,
                topic_reliability=reliability,
            )
        if not list(extension):
            root.remove(extension)
    return config


def _anchor_relative_files(root: ET.Element, base: Path) -> None:
    """Make file references absolute, since the stripped XML is compiled from a string."""
    base = base.resolve()
    compiler = root.find("compiler")
    if compiler is None:
        compiler = ET.Element("compiler")
        root.insert(0, compiler)
    for key in ("meshdir", "texturedir", "assetdir"):
        value = compiler.get(key)
        if value is not None and not Path(value).is_absolute():
            compiler.set(key, str(base / value))
    if compiler.get("meshdir") is None and compiler.get("texturedir") is None:
        compiler.set("assetdir", compiler.get("assetdir", str(base)))
    for include in root.iter("include"):
        file = include.get("file")
        if file and not Path(file).is_absolute():
            include.set("file", str(base / file))


def _ros2_control_block(source: str | Path) -> ET.Element:
    """The <ros2_control> element of a file or of XML text."""
    text = str(source)
    where = "ros2_control XML"
    if not text.lstrip().startswith("<"):
        path = Path(text).expanduser()
        try:
            text = path.read_text()
        except OSError as e:
            raise ModelError(f"{path}: {e.strerror}") from None
        where = str(path)
    try:
        root = ET.fromstring(text)
    except ET.ParseError as e:
        line, col = e.position
        raise ModelError(f"{where}:{line}:{col}: malformed XML: {_parse_reason(e)}") from None
    block = root if root.tag == "ros2_control" else root.find(".//ros2_control")
    if block is None:
        raise ModelError(f"{where}: no <ros2_control> element")
    return block


def _actuator_kind(m: mujoco.MjModel, i: int) -> InterfaceKind:
    """The command interface an actuator serves, from its gain and bias, as MJCF defines them."""
    bias = m.actuator_biasprm[i]
    affine = int(m.actuator_biastype[i]) == int(mujoco.mjtBias.mjBIAS_AFFINE)
    integrator = int(m.actuator_dyntype[i]) == int(mujoco.mjtDyn.mjDYN_INTEGRATOR)
    if affine and bias[1] != 0:
        # intvelocity integrates its velocity command into a position target
        return InterfaceKind.VELOCITY if integrator else InterfaceKind.POSITION
    if affine and bias[2] != 0:
        return InterfaceKind.VELOCITY
    return InterfaceKind.EFFORT


def _sensor_fields(type_name: str, dim: int) -> tuple[str, ...]:
    field, components = _SENSOR_FIELDS.get(type_name, ("value", ()))
    if components and len(components) == dim:
        return tuple(f"{field}.{c}" for c in components)
    if dim == 1:
        return (field,)
    return tuple(f"{field}.{k}" for k in range(dim))


def _discover(
    name: str,
    path: Path | None,
    m: mujoco.MjModel,
    xml: str,
    ros: RosPluginConfig | None,
    block: ET.Element | None,
) -> RobotSpec:
    one_dof = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
    joints = [
        Joint(m.joint(j).name, j, int(m.jnt_qposadr[j]), int(m.jnt_dofadr[j]))
        for j in range(m.njnt)
        if int(m.jnt_type[j]) in one_dof and m.joint(j).name
    ]

    commands: list[CommandInterface] = []
    taken: set[str] = set()
    joint_trn = (int(mujoco.mjtTrn.mjTRN_JOINT), int(mujoco.mjtTrn.mjTRN_JOINTINPARENT))
    for a in range(m.nu):
        act = m.actuator(a).name or f"actuator{a}"
        kind = _actuator_kind(m, a)
        joint = None
        if int(m.actuator_trntype[a]) in joint_trn:
            j = int(m.actuator_trnid[a, 0])
            if int(m.jnt_type[j]) in one_dof and m.joint(j).name:
                joint = m.joint(j).name
        iname = f"{joint or act}/{kind.value}"
        if iname in taken:  # a second actuator of one kind on one joint keeps its own name
            iname = f"{act}/{kind.value}"
        taken.add(iname)
        commands.append(CommandInterface(iname, kind, act, a, joint))

    sensors = []
    for s in range(m.nsensor):
        type_name = mujoco.mjtSensor(m.sensor_type[s]).name.removeprefix("mjSENS_").lower()
        dim = int(m.sensor_dim[s])
        objname = mujoco.mj_id2name(m, int(m.sensor_objtype[s]), int(m.sensor_objid[s]))
        sensors.append(
            Sensor(
                name=m.sensor(s).name or f"sensor{s}",
                type=type_name,
                adr=int(m.sensor_adr[s]),
                dim=dim,
                fields=_sensor_fields(type_name, dim),
                objname=objname,
            )
        )

    joint_states = {j.name: [k.value for k in InterfaceKind] for j in joints}
    problems: list[str] = []
    initial: dict[str, float] = {}
    if block is not None:
        joints, joint_states, commands, sensors = _narrow(
            block, joints, commands, sensors, problems, initial
        )
        for j in joints:  # a ros2_control initial_value is where the joint starts and resets to
            if j.name in initial:
                m.qpos0[j.qposadr] = initial[j.name]

    state: list[StateColumn] = []
    for j in joints:
        for kind in joint_states[j.name]:
            source, index = {
                "position": ("qpos", j.qposadr),
                "velocity": ("qvel", j.dofadr),
                "effort": ("qfrc_actuator", j.dofadr),
            }[kind]
            state.append(StateColumn(f"{j.name}/{kind}", source, index))
    for s in sensors:
        for k, field in enumerate(s.fields):
            state.append(StateColumn(f"{s.name}/{field}", "sensordata", s.adr + k))

    return RobotSpec(
        name=name,
        path=path,
        mjmodel=m,
        xml=xml,
        joints=joints,
        state=state,
        commands=commands,
        sensors=sensors,
        ros=ros,
        floating_base=floating_base(m),
        problems=problems,
    )


def floating_base(m: mujoco.MjModel) -> FloatingBase | None:
    """The free joint of the robot's own tree: the one its actuated joints (or actuated sites,
    bodies) hang from, so a free prop in the scene (a cube to grasp) is never taken for the
    base. A model without actuators has the first free joint as its base; a fixed-base robot
    beside free props has none.
    """
    free = [j for j in range(m.njnt) if int(m.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_FREE)]
    if not free:
        return None
    roots: dict[int, int] = {}  # tree root body -> actuators driving something in that tree
    for a in range(m.nu):
        trn, target = int(m.actuator_trntype[a]), int(m.actuator_trnid[a, 0])
        body = -1
        if trn in (int(mujoco.mjtTrn.mjTRN_JOINT), int(mujoco.mjtTrn.mjTRN_JOINTINPARENT)):
            body = int(m.jnt_bodyid[target])
        elif trn == int(mujoco.mjtTrn.mjTRN_SITE):
            body = int(m.site_bodyid[target])
        elif trn == int(mujoco.mjtTrn.mjTRN_BODY):
            body = target
        elif trn == int(mujoco.mjtTrn.mjTRN_TENDON):
            adr, num = int(m.tendon_adr[target]), int(m.tendon_num[target])
            for w in range(adr, adr + num):
                if int(m.wrap_type[w]) == int(mujoco.mjtWrap.mjWRAP_JOINT):
                    body = int(m.jnt_bodyid[int(m.wrap_objid[w])])
                    break
        if body > 0:
            root = int(m.body_rootid[body])
            roots[root] = roots.get(root, 0) + 1
    if m.nu == 0:
        chosen = free[0]
    else:
        driven = [j for j in free if roots.get(int(m.body_rootid[int(m.jnt_bodyid[j])]), 0) > 0]
        if not driven:
            return None
        chosen = max(driven, key=lambda j: roots[int(m.body_rootid[int(m.jnt_bodyid[j])])])
    body = int(m.jnt_bodyid[chosen])
    return FloatingBase(
        joint=m.joint(chosen).name or f"joint{chosen}",
        body=m.body(body).name or f"body{body}",
        qposadr=int(m.jnt_qposadr[chosen]),
        dofadr=int(m.jnt_dofadr[chosen]),
    )


def _narrow(
    block: ET.Element,
    joints: list[Joint],
    commands: list[CommandInterface],
    sensors: list[Sensor],
    problems: list[str],
    initial: dict[str, float],
) -> tuple[list[Joint], dict[str, list[str]], list[CommandInterface], list[Sensor]]:
    """Keep what a ros2_control block lists; record what it asks for and the model lacks."""
    by_name = {j.name: j for j in joints}
    kinds = [k.value for k in InterfaceKind]
    kept_joints: list[Joint] = []
    joint_states: dict[str, list[str]] = {}
    kept_commands: list[CommandInterface] = []
    for el in block.findall("joint"):
        jname = el.get("name", "")
        if jname not in by_name:
            problems.append(
                f"ros2_control joint {jname!r}: the model has no hinge or slide joint of that name"
            )
            continue
        kept_joints.append(by_name[jname])
        states = []
        for si in el.findall("state_interface"):
            iname = si.get("name", "")
            if iname not in kinds:
                problems.append(
                    f"ros2_control joint {jname!r}: unknown state interface {iname!r} "
                    f"(known: {', '.join(kinds)})"
                )
                continue
            states.append(iname)
            value = _param(si, "initial_value")
            if iname == "position" and value is not None:
                initial[jname] = value
        joint_states[jname] = states
        for ci in el.findall("command_interface"):
            iname = ci.get("name", "")
            match = [c for c in commands if c.joint == jname and c.kind.value == iname]
            if not match:
                served = [c.kind.value for c in commands if c.joint == jname]
                problems.append(
                    f"ros2_control joint {jname!r}: no actuator serves command interface "
                    f"{jname}/{iname} (actuators on this joint serve: "
                    f"{', '.join(served) or 'none'})"
                )
                continue
            kept_commands.extend(match)
    kept_joints.sort(key=lambda j: j.id)
    kept_commands.sort(key=lambda c: c.actuator_id)

    listed = block.findall("sensor")
    if listed:
        names = {s.name: s for s in sensors}
        kept_sensors = []
        for el in listed:
            sname = el.get("name", "")
            if sname not in names:
                problems.append(f"ros2_control sensor {sname!r}: the model has no sensor of that name")
            else:
                kept_sensors.append(names[sname])
        sensors = sorted(kept_sensors, key=lambda s: s.adr)
    return kept_joints, joint_states, kept_commands, sensors


def _param(el: ET.Element, name: str) -> float | None:
    for p in el.findall("param"):
        if p.get("name") == name and p.text is not None:
            try:
                return float(p.text)
            except ValueError:
                return None
    return None


def initial_command(spec: RobotSpec) -> np.ndarray:
    """The command each interface starts with: hold the initial pose, zero velocity and effort."""
    m = spec.mjmodel
    out = np.zeros(len(spec.commands))
    for c, cmd in enumerate(spec.commands):
        if cmd.kind is InterfaceKind.POSITION and cmd.joint is not None:
            out[c] = m.qpos0[m.joint(cmd.joint).qposadr[0]]
    return out
