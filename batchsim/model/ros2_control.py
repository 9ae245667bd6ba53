"""What a robot description's `<ros2_control>` blocks make of an MJCF, as mujoco_ros2_control
reads them.

- A `<joint name="J">` is served by the actuators on MuJoCo joint `J`, or else by the
  actuator named `J` (a tendon- or site-driven gripper, a coupled finger, a site-velocity
  base). Its command interfaces are those its actuators' gain and bias make them
  (`torque` and `force` are names of `effort`); a `position` or `velocity` interface on a
  torque motor (or a `position` one on a velocity actuator) runs through a PID whose gains
  come from the block's `pids_config_file` (`pid_gains.position.J`, `pid_gains.velocity.J`).
- A position interface whose actuator takes control units (Robotiq's 0-255) and whose
  `<command_interface>` gives `min` and `max` is scaled: `[min, max]` maps onto the
  actuator's `ctrlrange`.
- Mimic joints (`<param name="mimic">`, or a URDF `<mimic>`) take no commands; an actuator on
  one follows the mimicked joint's command times `multiplier` plus `offset`.
- A `<sensor>` with `mujoco_type` (`fts`, `imu`, `pose`, `magnetometer`) reads the MJCF
  sensors `<mujoco_sensor_name><suffix>` (`_force`/`_torque`, `_quat`/`_gyro`/`_accel`,
  `_pos`/`_quat`); one without reads the MJCF sensor of its own name.
- `initial_value` on a position state interface sets where the joint starts;
  `initial_keyframe` names the keyframe worlds start in.

Problems (a joint the model lacks, a command interface nothing can serve) are collected,
not raised: `on_configure` reports them, as a hardware component does in ros2_control.
Anything not acted on is a warning.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from pathlib import Path

import mujoco

from batchsim.model.description import ComponentInfo, Description
from batchsim.model.lidars import rangefinder_groups
from batchsim.model.params import ParamsError, nest_dotted, node_parameters, read_yaml
from batchsim.model.spec import (
    CommandInterface,
    CommandMode,
    InterfaceKind,
    Joint,
    MimicCommand,
    Sensor,
    StateColumn,
    Transmission,
)
from batchsim.model.transmissions import Transmitted, transmissions
from batchsim.pid import PidGains
from batchsim.types import StateSource

# mujoco_type -> {state interface field: (MJCF sensor suffix param, default suffix, component)}
_XYZ = ("x", "y", "z")
_MUJOCO_TYPES: dict[str, list[tuple[str, str, str, int, str]]] = {
    # (field prefix, suffix param, default suffix, MuJoCo sensor type, component order)
    "fts": [("force", "force_mjcf_suffix", "_force", mujoco.mjtSensor.mjSENS_FORCE, "xyz"),
            ("torque", "torque_mjcf_suffix", "_torque", mujoco.mjtSensor.mjSENS_TORQUE, "xyz")],
    "imu": [("orientation", "orientation_mjcf_suffix", "_quat", mujoco.mjtSensor.mjSENS_FRAMEQUAT, "wxyz"),
            ("angular_velocity", "angular_velocity_mjcf_suffix", "_gyro", mujoco.mjtSensor.mjSENS_GYRO, "xyz"),
            ("linear_acceleration", "linear_acceleration_mjcf_suffix", "_accel",
             mujoco.mjtSensor.mjSENS_ACCELEROMETER, "xyz")],
    "pose": [("position", "position_mjcf_suffix", "_pos", mujoco.mjtSensor.mjSENS_FRAMEPOS, "xyz"),
             ("orientation", "orientation_mjcf_suffix", "_quat", mujoco.mjtSensor.mjSENS_FRAMEQUAT, "wxyz")],
    "magnetometer": [("magnetic_field", "", "", mujoco.mjtSensor.mjSENS_MAGNETOMETER, "xyz")],
}
_KIND_ORDER = {InterfaceKind.POSITION: 0, InterfaceKind.VELOCITY: 1, InterfaceKind.EFFORT: 2}


@dataclasses.dataclass(frozen=True)
class Actuator:
    """A MuJoCo actuator as the ros2_control mapping sees it."""

    name: str
    id: int
    kind: InterfaceKind  # what its gain and bias make it
    joint: str | None  # the hinge/slide joint it drives, or the joint it is named after (tendon)
    control_units: bool  # a position actuator whose ctrl is not in the joint's units (gain != kp)


@dataclasses.dataclass
class Narrowed:
    """What the blocks keep and ask for."""

    joints: list[Joint]
    joint_states: dict[str, list[str]]  # joint -> state interface names, as the block spells them
    commands: list[CommandInterface]
    sensors: list[Sensor]
    sensor_columns: list[StateColumn]  # mujoco_type sensors' state interfaces
    initial_values: dict[str, float]
    mimics: list[MimicCommand]
    keyframe: str | None  # the initial_keyframe param
    odom_joint: str | None  # the odom_free_joint_name param
    problems: list[str]
    warnings: list[str]
    transmissions: list[Transmission] = dataclasses.field(default_factory=list)
    actuator_commands: list[CommandInterface] | None = None  # with transmissions: what drives ctrl
    actuator_space: list[Joint] = dataclasses.field(default_factory=list)  # transmissions' actuators' joints


def narrow(
    description: Description,
    m: mujoco.MjModel,
    joints: list[Joint],
    actuators: list[Actuator],
    sensors: list[Sensor],
) -> Narrowed:
    """Keep what the blocks list; record what they ask for and the model lacks."""
    out = Narrowed([], {}, [], [], [], {}, [], None, None, [], list(description.warnings))
    problems = out.problems
    by_joint = {j.name: j for j in joints}
    pids = _pid_gains(description, out)
    for key, name in (("initial_keyframe", "keyframe"), ("odom_free_joint_name", "odom_joint")):
        found = description.param(key)
        if found is not None:
            setattr(out, name, found[0])

    components = {el.name: el for el in description.joints}
    actuated = {a.joint for a in actuators if a.joint} | {a.name for a in actuators}
    tr = transmissions(description.transmissions, components, by_joint, actuated, problems)
    seen: set[str] = set()
    commands: list[CommandInterface] = []
    inner: dict[str, CommandInterface | None] = {}  # the transmissions' actuators' interfaces (None: cannot be)
    mimic_joints: list[ComponentInfo] = []
    for el in description.joints:
        jname = el.name
        if jname in seen:
            problems.append(f"ros2_control joint {jname!r}: listed in two blocks")
            continue
        seen.add(jname)
        if jname in tr.by_joint:
            _transmitted(el, tr, by_joint, actuators, pids, m, commands, inner, out)
            continue
        serving = [a for a in actuators if a.joint == jname] or [a for a in actuators if a.name == jname]
        joint = by_joint.get(jname)
        if joint is None and not serving:
            problems.append(
                f"ros2_control joint {jname!r}: the model has no hinge or slide joint and no actuator of that name"
            )
            continue
        if joint is not None:
            out.joints.append(joint)
            out.joint_states[jname] = _joint_states(el, jname, out)
        elif el.state_interfaces:
            out.warnings.append(
                f"ros2_control joint {jname!r}: actuator {jname!r} drives no joint of that name, so its "
                f"state interfaces ({', '.join(s.name for s in el.state_interfaces)}) are not available"
            )
        if el.mimic is not None:
            mimic_joints.append(el)
            if el.command_interfaces:
                out.warnings.append(
                    f"ros2_control joint {jname!r}: a mimic joint: its command interfaces are ignored "
                    f"(it follows {el.mimic.joint!r})"
                )
            continue
        for ci in el.command_interfaces:
            cmd = _command(el, ci.name, ci.params, joint, serving, pids, m, out)
            if cmd is not None:
                commands.append(cmd)
    order = {a.id: k for k, a in enumerate(actuators)}

    def key(c: CommandInterface) -> tuple[int, int]:
        if c.mode is CommandMode.TRANSMITTED:  # where its paired actuator's interface sorts
            t, k = tr.by_joint[c.joint]
            c = inner[f"{t.actuators[k]}/{c.name.rsplit('/', 1)[1]}"]
        return order[c.actuator_id], _KIND_ORDER[c.kind]

    commands.sort(key=key)
    out.commands = commands
    if tr.transmissions:
        out.transmissions, out.actuator_space = tr.transmissions, list(tr.actuator_joints.values())
        out.actuator_commands = sorted(
            [c for c in commands if c.mode is not CommandMode.TRANSMITTED] + [c for c in inner.values() if c], key=key
        )
        _transmit_initial_values(tr, out)
    out.joints.sort(key=lambda j: j.id)
    for el in mimic_joints:
        _mimic(el, actuators, commands, out)
    _sensors(description, m, sensors, out)
    return out


def _transmitted(
    el: ComponentInfo,
    tr: Transmitted,
    by_joint: dict[str, Joint],
    actuators: list[Actuator],
    pids: dict[tuple[str, str], PidGains],
    m: mujoco.MjModel,
    commands: list[CommandInterface],
    inner: dict[str, CommandInterface | None],
    out: Narrowed,
) -> None:
    """A joint behind a transmission: state read at its paired actuator and mapped; each
    command interface TRANSMITTED onto the same interface of every actuator of its transmission."""
    jname = el.name
    t, _ = tr.by_joint[jname]
    out.joints.append(tr.paired(jname))
    out.joint_states[jname] = _joint_states(el, jname, out)
    if el.mimic is not None:
        out.warnings.append(f"ros2_control joint {jname!r}: a transmission's joint: its mimic is ignored")
    for ci in el.command_interfaces:
        kind = InterfaceKind.of_name(ci.name)
        if kind is None:
            out.problems.append(f"ros2_control joint {jname!r}: unknown command interface {ci.name!r}")
            continue
        for a in t.actuators:
            name = f"{a}/{ci.name}"
            if name not in inner:  # once per actuator: the transmission's other joint shares it
                serving = [x for x in actuators if x.joint == a] or [x for x in actuators if x.name == a]
                component = ComponentInfo(a, {}, (), ())
                inner[name] = _command(component, ci.name, ci.params, by_joint[a], serving, pids, m, out)
        if any(inner[f"{a}/{ci.name}"] is None for a in t.actuators):
            continue
        commands.append(
            CommandInterface(f"{jname}/{ci.name}", kind, t.name, -1, jname, mode=CommandMode.TRANSMITTED)
        )


def _transmit_initial_values(tr: Transmitted, out: Narrowed) -> None:
    """initial_value of a transmission's joints -> its actuators' joints' (all of them, or none)."""
    for t in tr.transmissions:
        given = [j for j in t.joints if j in out.initial_values]
        values = [out.initial_values.pop(j) for j in given]
        if not given:
            continue
        if len(given) < len(t.joints):
            out.warnings.append(
                f"ros2_control transmission {t.name!r}: initial_value of {', '.join(given)} ignored: "
                "give one to every joint of the transmission"
            )
            continue
        for row, a in zip(t.matrix, t.actuators, strict=True):
            out.initial_values[a] = sum(c * (v - o) for c, v, o in zip(row, values, t.offset, strict=True))


def _joint_states(el: ComponentInfo, jname: str, out: Narrowed) -> list[str]:
    states = []
    for si in el.state_interfaces:
        kind = InterfaceKind.of_name(si.name)
        if kind is None:
            out.problems.append(
                f"ros2_control joint {jname!r}: unknown state interface {si.name!r} "
                f"(known: position, velocity, effort, torque, force)"
            )
            continue
        states.append(si.name)
        value = si.params.get("initial_value")
        if kind is InterfaceKind.POSITION and value not in (None, ""):
            try:
                out.initial_values[jname] = float(value)
            except ValueError:
                out.problems.append(
                    f"ros2_control joint {jname!r}: initial_value {value!r} is not a number"
                )
    return states


def _command(
    el: ComponentInfo,
    iname: str,
    params: Mapping[str, str],
    joint: Joint | None,
    serving: list[Actuator],
    pids: dict[tuple[str, str], PidGains],
    m: mujoco.MjModel,
    out: Narrowed,
) -> CommandInterface | None:
    jname = el.name
    kind = InterfaceKind.of_name(iname)
    served = ", ".join(f"{a.kind.value} ({a.name})" for a in serving) or "none"
    if kind is None:
        out.problems.append(
            f"ros2_control joint {jname!r}: unknown command interface {iname!r} "
            f"(known: position, velocity, effort, torque, force)"
        )
        return None
    name = f"{jname}/{iname}"
    direct = [a for a in serving if a.kind is kind]
    if direct:
        a = direct[0]
        scale, offset = 1.0, 0.0
        if kind is InterfaceKind.POSITION and a.control_units:
            scale, offset = _gripper_scaling(jname, iname, params, a, m, out)
        return CommandInterface(name, kind, a.name, a.id, a.joint, scale=scale, offset=offset)
    # a position/velocity interface on a motor, or a position one on a velocity actuator: a PID
    mode = {InterfaceKind.POSITION: CommandMode.POSITION_PID, InterfaceKind.VELOCITY: CommandMode.VELOCITY_PID}
    for a in serving:
        can = a.kind is InterfaceKind.EFFORT or (a.kind is InterfaceKind.VELOCITY and kind is InterfaceKind.POSITION)
        if kind is InterfaceKind.EFFORT or not can:
            continue
        key = a.joint or a.name
        gains = pids.get((kind.value, key))
        if gains is None:
            out.problems.append(
                f"ros2_control joint {jname!r}: {iname} on {a.kind.value} actuator {a.name!r} needs PID gains "
                f"(pid_gains.{kind.value}.{key} in the pids_config_file)"
            )
            return None
        if joint is None:
            out.problems.append(
                f"ros2_control joint {jname!r}: a PID needs the joint's {kind.value}, and actuator "
                f"{a.name!r} drives no joint of that name"
            )
            return None
        return CommandInterface(
            name, kind, a.name, a.id, a.joint, mode=mode[kind], pid=gains,
            qposadr=joint.qposadr, dofadr=joint.dofadr,
        )
    position = next((a for a in serving if a.kind is InterfaceKind.POSITION), None)
    beside = any(ci.name == "position" for ci in el.command_interfaces)
    if kind is InterfaceKind.VELOCITY and position is not None and beside:
        # beside the servo's own position interface (which stays the active one), as
        # mujoco_ros2_control exports it: its PID configuration with a URDF-generated MJCF lists
        # it; made active, the velocity goes to the servo's ctrl as is. Alone, it is a problem.
        out.warnings.append(
            f"ros2_control joint {jname!r}: {name} on position actuator {position.name!r}: served as "
            "mujoco_ros2_control serves it, the value written to the servo's ctrl as a position target"
        )
        return CommandInterface(name, kind, position.name, position.id, position.joint)
    out.problems.append(
        f"ros2_control joint {jname!r}: no actuator serves command interface {name} "
        f"(actuators on this joint serve: {served})"
    )
    return None


def _gripper_scaling(
    jname: str, iname: str, params: Mapping[str, str], a: Actuator, m: mujoco.MjModel, out: Narrowed
) -> tuple[float, float]:
    """ctrl = scale * command + offset mapping the interface's [min, max] onto ctrlrange."""
    lo, hi = (float(v) for v in m.actuator_ctrlrange[a.id])
    try:
        cmin, cmax = float(params["min"]), float(params["max"])
    except (KeyError, ValueError):
        out.warnings.append(
            f"ros2_control joint {jname!r}: actuator {a.name!r} takes {iname} in control units "
            f"(ctrlrange {lo:g} {hi:g}); give the joint's range as <param name=\"min\"> and "
            f"<param name=\"max\"> on its {iname} command interface to command it in metres or radians"
        )
        return 1.0, 0.0
    if not m.actuator_ctrllimited[a.id] or not cmax > cmin:
        out.problems.append(
            f"ros2_control joint {jname!r}: {iname} min/max {cmin:g}/{cmax:g} cannot be scaled onto "
            f"actuator {a.name!r} (it needs a ctrlrange and min < max)"
        )
        return 1.0, 0.0
    scale = (hi - lo) / (cmax - cmin)
    return scale, lo - scale * cmin


def _mimic(el: ComponentInfo, actuators: list[Actuator], commands: list[CommandInterface], out: Narrowed) -> None:
    mimic = el.mimic
    sources = [c for c in commands if c.name.rsplit("/", 1)[0] == mimic.joint]
    if not any(j.name == mimic.joint for j in out.joints) and not sources:
        out.problems.append(
            f"ros2_control joint {el.name!r}: mimics {mimic.joint!r}, which no block lists"
        )
        return
    own = [a for a in actuators if a.joint == el.name and a.name != mimic.joint]
    for a in own:
        source = next((c for c in sources if c.kind is a.kind and c.mode is CommandMode.DIRECT), None)
        if source is None:
            out.warnings.append(
                f"ros2_control joint {el.name!r}: its {a.kind.value} actuator {a.name!r} has no "
                f"{a.kind.value} command of {mimic.joint!r} to follow; it keeps its initial ctrl"
            )
            continue
        offset = mimic.offset if a.kind is InterfaceKind.POSITION else 0.0
        out.mimics.append(MimicCommand(el.name, source.name, a.name, a.id, mimic.multiplier, offset))


def _sensors(description: Description, m: mujoco.MjModel, sensors: list[Sensor], out: Narrowed) -> None:
    listed = description.sensors
    if not listed:
        out.sensors = sensors
        return
    by_name = {s.name: s for s in sensors}
    bridged = {m.camera(c).name for c in range(m.ncam)} | {g.name for g in rangefinder_groups(m)}
    kept: list[Sensor] = []
    for el in listed:
        mujoco_type = el.params.get("mujoco_type")
        if mujoco_type is None:
            if el.name in by_name:
                kept.append(by_name[el.name])
            elif el.name not in bridged:  # a camera's or lidar's: its params configure the bridge's topics
                out.warnings.append(
                    f"ros2_control sensor {el.name!r}: no mujoco_type and no MJCF sensor of that name: "
                    "not a state interface (cameras and lidars are served by the bridge)"
                )
            continue
        parts = _MUJOCO_TYPES.get(mujoco_type)
        if parts is None:
            out.problems.append(
                f"ros2_control sensor {el.name!r}: unknown mujoco_type {mujoco_type!r} "
                f"(known: {', '.join(_MUJOCO_TYPES)})"
            )
            continue
        base = el.params.get("mujoco_sensor_name", el.name)
        wanted = {si.name for si in el.state_interfaces}
        for field, suffix_param, default, sensor_type, order in parts:
            suffix = el.params.get(suffix_param) if suffix_param else ""
            if suffix is None:
                found = description.param(suffix_param)
                suffix = found[0] if found else default
            mjname = base + suffix
            sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SENSOR, mjname)
            if sid < 0 or int(m.sensor_type[sid]) != int(sensor_type):
                out.problems.append(
                    f"ros2_control sensor {el.name!r} (mujoco_type {mujoco_type}): the model has no "
                    f"{sensor_type.name.removeprefix('mjSENS_').lower()} sensor {mjname!r}"
                )
                continue
            adr = int(m.sensor_adr[sid])
            # mujoco_ros2_control reports a force/torque sensor's reading negated: the load on the sensor
            sign = -1.0 if mujoco_type == "fts" else 1.0
            for k, component in enumerate(order):
                name = f"{field}.{component}"
                if wanted and name not in wanted:
                    continue
                out.sensor_columns.append(StateColumn(f"{el.name}/{name}", StateSource.SENSORDATA, adr + k, sign))
        known = {c.name.split("/", 1)[1] for c in out.sensor_columns if c.name.startswith(el.name + "/")}
        for name in sorted(wanted - known):
            if not name.endswith("covariance") and not any(name.startswith(p[0]) for p in parts):
                out.warnings.append(f"ros2_control sensor {el.name!r}: state interface {name!r}: ignored")
    out.sensors = sorted(kept, key=lambda s: s.adr)


def _pid_gains(description: Description, out: Narrowed) -> dict[tuple[str, str], PidGains]:
    """(position|velocity, joint) -> gains, from every block's pids_config_file."""
    gains: dict[tuple[str, str], PidGains] = {}
    for hw in description.hardware:
        file = hw.params.get("pids_config_file", "").strip()
        if not file:
            continue
        path = Path(file).expanduser()
        if not path.is_absolute() and description.directory is not None:
            path = description.directory / path
        try:
            params = nest_dotted(node_parameters(read_yaml(path), None, str(path)))
        except ParamsError as e:
            out.problems.append(f"pids_config_file: {e}")
            continue
        table = params.get("pid_gains")
        if not isinstance(table, Mapping):
            out.problems.append(f"{path}: no pid_gains: position|velocity: <joint>: block")
            continue
        for mode, joints in table.items():
            if mode not in ("position", "velocity") or not isinstance(joints, Mapping):
                out.warnings.append(f"{path}: pid_gains.{mode}: ignored: expected position or velocity")
                continue
            for joint, values in joints.items():
                where = f"{path}: pid_gains.{mode}.{joint}"
                if not isinstance(values, Mapping):
                    out.problems.append(f"{where}: expected a mapping of gains (p, i, d, ...)")
                    continue
                try:
                    g, warnings = PidGains.from_params(values, where)
                except ValueError as e:
                    out.problems.append(str(e))
                    continue
                out.warnings += warnings
                if not all(math.isfinite(v) for v in (g.p, g.i, g.d)):
                    out.problems.append(f"{where}: p, i and d must be finite")
                    continue
                gains[(mode, str(joint))] = g
    return gains
