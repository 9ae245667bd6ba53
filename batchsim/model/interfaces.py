"""Interface discovery: what an MJCF exposes, named the way ros2_control names things.

- every hinge or slide joint gets the state interfaces `<joint>/position`, `/velocity`
  and `/effort`;
- every actuator gets a command interface by its type, as ros2_control users expect: a
  `motor` is `effort`, a `position` actuator is `position`, a `velocity` (or
  `intvelocity`) actuator is `velocity`; it is named after its joint
  (`joint1/position`) when it drives one, else after itself;
- every sensor is exposed with ros2_control-style field names (`wrist_force/force.x`);
- the floating base is the free joint of the robot's own tree;
- a `<ros2_control>` block narrows all of it (`batchsim.model.ros2_control`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import mujoco
import numpy as np

from batchsim.model.description import Description
from batchsim.model.ros2_control import Actuator, narrow
from batchsim.model.spec import (
    CommandInterface,
    CommandMode,
    FloatingBase,
    InitialState,
    InterfaceKind,
    Joint,
    MimicCommand,
    ModelError,
    RobotSpec,
    RosPluginConfig,
    Sensor,
    StateColumn,
)
from batchsim.types import StateSource

# Field names of each MuJoCo sensor type's components, ros2_control style.
_XYZ = ("x", "y", "z")
_WXYZ = ("w", "x", "y", "z")
_SENSOR_FIELDS: dict[mujoco.mjtSensor, tuple[str, tuple[str, ...]]] = {
    mujoco.mjtSensor.mjSENS_TOUCH: ("force", ()),
    mujoco.mjtSensor.mjSENS_ACCELEROMETER: ("linear_acceleration", _XYZ),
    mujoco.mjtSensor.mjSENS_VELOCIMETER: ("linear_velocity", _XYZ),
    mujoco.mjtSensor.mjSENS_GYRO: ("angular_velocity", _XYZ),
    mujoco.mjtSensor.mjSENS_FORCE: ("force", _XYZ),
    mujoco.mjtSensor.mjSENS_TORQUE: ("torque", _XYZ),
    mujoco.mjtSensor.mjSENS_MAGNETOMETER: ("magnetic_field", _XYZ),
    mujoco.mjtSensor.mjSENS_RANGEFINDER: ("range", ()),
    mujoco.mjtSensor.mjSENS_JOINTPOS: ("position", ()),
    mujoco.mjtSensor.mjSENS_JOINTVEL: ("velocity", ()),
    mujoco.mjtSensor.mjSENS_TENDONPOS: ("position", ()),
    mujoco.mjtSensor.mjSENS_TENDONVEL: ("velocity", ()),
    mujoco.mjtSensor.mjSENS_ACTUATORPOS: ("position", ()),
    mujoco.mjtSensor.mjSENS_ACTUATORVEL: ("velocity", ()),
    mujoco.mjtSensor.mjSENS_ACTUATORFRC: ("effort", ()),
    mujoco.mjtSensor.mjSENS_JOINTACTFRC: ("effort", ()),
    mujoco.mjtSensor.mjSENS_TENDONACTFRC: ("effort", ()),
    mujoco.mjtSensor.mjSENS_BALLQUAT: ("orientation", _WXYZ),
    mujoco.mjtSensor.mjSENS_BALLANGVEL: ("angular_velocity", _XYZ),
    mujoco.mjtSensor.mjSENS_FRAMEPOS: ("position", _XYZ),
    mujoco.mjtSensor.mjSENS_FRAMEQUAT: ("orientation", _WXYZ),
    mujoco.mjtSensor.mjSENS_FRAMEXAXIS: ("x_axis", _XYZ),
    mujoco.mjtSensor.mjSENS_FRAMEYAXIS: ("y_axis", _XYZ),
    mujoco.mjtSensor.mjSENS_FRAMEZAXIS: ("z_axis", _XYZ),
    mujoco.mjtSensor.mjSENS_FRAMELINVEL: ("linear_velocity", _XYZ),
    mujoco.mjtSensor.mjSENS_FRAMEANGVEL: ("angular_velocity", _XYZ),
    mujoco.mjtSensor.mjSENS_FRAMELINACC: ("linear_acceleration", _XYZ),
    mujoco.mjtSensor.mjSENS_FRAMEANGACC: ("angular_acceleration", _XYZ),
    mujoco.mjtSensor.mjSENS_SUBTREECOM: ("position", _XYZ),
    mujoco.mjtSensor.mjSENS_SUBTREELINVEL: ("linear_velocity", _XYZ),
    mujoco.mjtSensor.mjSENS_SUBTREEANGMOM: ("angular_momentum", _XYZ),
    mujoco.mjtSensor.mjSENS_CLOCK: ("time", ()),
}



def _actuator_kind(m: mujoco.MjModel, i: int) -> InterfaceKind:
    """The command interface an actuator serves, from its gain and bias, as mujoco_ros2_control
    classifies it: no bias is a motor (effort), an affine bias on the length a position servo,
    on the velocity alone a velocity servo (intvelocity integrates velocity into a position
    target); anything else takes effort-like ctrl too."""
    bias = m.actuator_biasprm[i]
    affine = int(m.actuator_biastype[i]) == int(mujoco.mjtBias.mjBIAS_AFFINE)
    integrator = int(m.actuator_dyntype[i]) == int(mujoco.mjtDyn.mjDYN_INTEGRATOR)
    if affine and bias[1] != 0:
        return InterfaceKind.VELOCITY if integrator else InterfaceKind.POSITION
    if affine and bias[2] != 0:
        return InterfaceKind.VELOCITY
    return InterfaceKind.EFFORT


def _actuators(m: mujoco.MjModel, one_dof: tuple[int, int]) -> list[Actuator]:
    """Every actuator with the joint it drives: its joint's, or for a tendon or site actuator
    the joint it is named after (mujoco_ros2_control's convention), else None."""
    joint_trn = (int(mujoco.mjtTrn.mjTRN_JOINT), int(mujoco.mjtTrn.mjTRN_JOINTINPARENT))
    out = []
    for a in range(m.nu):
        name = m.actuator(a).name or f"actuator{a}"
        kind = _actuator_kind(m, a)
        joint = None
        if int(m.actuator_trntype[a]) in joint_trn:
            j = int(m.actuator_trnid[a, 0])
            if int(m.jnt_type[j]) in one_dof and m.joint(j).name:
                joint = m.joint(j).name
        else:
            j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)
            if j >= 0 and int(m.jnt_type[j]) in one_dof:
                joint = name
        gain, bias = float(m.actuator_gainprm[a, 0]), float(m.actuator_biasprm[a, 1])
        control_units = kind is InterfaceKind.POSITION and not np.isclose(gain, -bias, rtol=1e-6, atol=0)
        out.append(Actuator(name, a, kind, joint, bool(control_units)))
    return out


def _sensor_fields(sensor_type: mujoco.mjtSensor, dim: int) -> tuple[str, ...]:
    field, components = _SENSOR_FIELDS.get(sensor_type, ("value", ()))
    if components and len(components) == dim:
        return tuple(f"{field}.{c}" for c in components)
    if dim == 1:
        return (field,)
    return tuple(f"{field}.{k}" for k in range(dim))


def discover(
    name: str,
    path: Path | None,
    m: mujoco.MjModel,
    xml: str,
    ros: RosPluginConfig | None,
    description: Description | None,
    *,
    keyframe: str | int | None = None,
    key_ctrl_given: Sequence[bool] = (),
) -> RobotSpec:
    """The RobotSpec of a compiled model: its interfaces, narrowed by the description's
    ros2_control blocks if it has any, and the state its worlds start in."""
    one_dof = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
    joints = [
        Joint(m.joint(j).name, j, int(m.jnt_qposadr[j]), int(m.jnt_dofadr[j]))
        for j in range(m.njnt)
        if int(m.jnt_type[j]) in one_dof and m.joint(j).name
    ]
    actuators = _actuators(m, one_dof)

    commands: list[CommandInterface] = []
    taken: set[str] = set()
    for a in actuators:
        iname = f"{a.joint or a.name}/{a.kind.value}"
        if iname in taken:  # a second actuator of one kind on one joint keeps its own name
            iname = f"{a.name}/{a.kind.value}"
        taken.add(iname)
        commands.append(CommandInterface(iname, a.kind, a.name, a.id, a.joint))

    sensors = []
    for s in range(m.nsensor):
        sensor_type = mujoco.mjtSensor(m.sensor_type[s])
        dim = int(m.sensor_dim[s])
        objname = mujoco.mj_id2name(m, int(m.sensor_objtype[s]), int(m.sensor_objid[s]))
        sensors.append(
            Sensor(
                name=m.sensor(s).name or f"sensor{s}",
                type=sensor_type,
                adr=int(m.sensor_adr[s]),
                dim=dim,
                fields=_sensor_fields(sensor_type, dim),
                objname=objname,
            )
        )

    joint_states = {j.name: [k.value for k in InterfaceKind] for j in joints}
    problems: list[str] = []
    warnings: list[str] = []
    initial_values: dict[str, float] = {}
    sensor_columns: list[StateColumn] = []
    mimics: list[MimicCommand] = []
    block_keyframe = odom_joint = None
    transmissions, actuator_commands, actuator_space = [], None, []
    if description is not None:
        n = narrow(description, m, joints, actuators, sensors)
        joints, joint_states, commands, sensors = n.joints, n.joint_states, n.commands, n.sensors
        sensor_columns, initial_values, mimics = n.sensor_columns, n.initial_values, n.mimics
        problems, warnings, block_keyframe, odom_joint = n.problems, n.warnings, n.keyframe, n.odom_joint
        transmissions, actuator_commands, actuator_space = n.transmissions, n.actuator_commands, n.actuator_space
    start = initial_state(
        m, keyframe, block_keyframe, key_ctrl_given, initial_values, joints + actuator_space, problems, warnings
    )

    state: list[StateColumn] = []
    for j in joints:
        for iname in joint_states[j.name]:
            source, index = {
                InterfaceKind.POSITION: (StateSource.QPOS, j.qposadr),
                InterfaceKind.VELOCITY: (StateSource.QVEL, j.dofadr),
                InterfaceKind.EFFORT: (StateSource.QFRC_ACTUATOR, j.dofadr),
            }[InterfaceKind.of_name(iname)]
            state.append(StateColumn(f"{j.name}/{iname}", source, index))
    for s in sensors:
        for k, field in enumerate(s.fields):
            state.append(StateColumn(f"{s.name}/{field}", StateSource.SENSORDATA, s.adr + k))
    state += sensor_columns

    base = floating_base(m)
    if odom_joint is not None:
        jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, odom_joint)
        if jid < 0 or int(m.jnt_type[jid]) != int(mujoco.mjtJoint.mjJNT_FREE):
            problems.append(f"ros2_control odom_free_joint_name {odom_joint!r}: the model has no free joint of that name")
        else:
            body = int(m.jnt_bodyid[jid])
            base = FloatingBase(odom_joint, m.body(body).name or f"body{body}",
                                int(m.jnt_qposadr[jid]), int(m.jnt_dofadr[jid]))

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
        floating_base=base,
        initial=start,
        keyframes=[m.key(k).name for k in range(m.nkey)],
        mimics=mimics,
        problems=problems,
        warnings=warnings,
        transmissions=transmissions,
        actuator_commands=actuator_commands,
        actuator_joints=_actuator_joints(m, actuators, one_dof),
    )


def _actuator_joints(m: mujoco.MjModel, actuators: list[Actuator], one_dof: tuple[int, int]) -> list[tuple[str, int, int]]:
    """What mujoco_ros2_control reports on mujoco_actuators_states: each actuator under its
    joint's name (its own for a tendon or site), then every hinge/slide joint none drives."""
    out: dict[str, tuple[str, int, int]] = {}
    for a in actuators:
        name = a.joint or a.name
        j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)
        found = j >= 0 and int(m.jnt_type[j]) in one_dof
        out.setdefault(name, (name, int(m.jnt_qposadr[j]), int(m.jnt_dofadr[j])) if found else (name, -1, -1))
    driven = {adr for _, adr, _ in out.values()}
    for j in range(m.njnt):
        if int(m.jnt_type[j]) in one_dof and m.joint(j).name and int(m.jnt_qposadr[j]) not in driven:
            out.setdefault(m.joint(j).name, (m.joint(j).name, int(m.jnt_qposadr[j]), int(m.jnt_dofadr[j])))
    return list(out.values())


def initial_state(
    m: mujoco.MjModel,
    keyframe: str | int | None,
    block_keyframe: str | None,
    key_ctrl_given: Sequence[bool],
    initial_values: dict[str, float],
    joints: list[Joint],
    problems: list[str],
    warnings: list[str],
) -> InitialState:
    """Where worlds start: the keyframe asked for (`keyframe`, else the block's
    initial_keyframe), else `home` if the model has one, else qpos0; a ros2_control
    initial_value then sets its joint's qpos unless a keyframe was asked for by name
    (mujoco_ros2_control's rule: a named keyframe overrides initial values)."""
    names = [m.key(k).name for k in range(m.nkey)]
    asked = keyframe if keyframe is not None else block_keyframe
    key: int | None = None
    if asked is not None:
        key = _keyframe_index(asked, names)
        if key is None:
            known = ", ".join(repr(n) if n else f"#{k}" for k, n in enumerate(names)) or "none"
            message = f"no keyframe {asked!r} (keyframes: {known})"
            if keyframe is not None:
                raise ModelError(message)
            problems.append(f"ros2_control initial_keyframe: {message}")
    elif "home" in names:
        key = names.index("home")
    if key is None:
        start = InitialState.of_model(m)
        if names and asked is None:  # keyframes, none of them `home`: say what qpos0 is like
            d = mujoco.MjData(m)
            mujoco.mj_forward(m, d)
            known = ", ".join(repr(n) if n else f"#{k}" for k, n in enumerate(names))
            warnings.append(
                f"starts in qpos0 ({d.ncon} contacts there): the model has no keyframe 'home'; its keyframes: "
                f"{known} (choose one with --keyframe, or make(..., keyframe=))"
            )
    else:
        label = repr(names[key]) if names[key] else f"#{key}"
        given = bool(key_ctrl_given[key]) if key < len(key_ctrl_given) else False
        start = InitialState.of_keyframe(m, key, label, given)
    if initial_values:
        if asked is not None and key is not None:
            warnings.append(
                f"ros2_control initial_value of {', '.join(sorted(initial_values))}: ignored: keyframe "
                f"{start.keyframe} sets the initial state"
            )
        else:
            for j in joints:
                if j.name in initial_values:
                    start.qpos[j.qposadr] = initial_values[j.name]
                    _hold(m, start, j)
            start.initial_values = True
    return start


def _hold(m: mujoco.MjModel, start: InitialState, joint: Joint) -> None:
    """A keyframe's ctrl for position servos on a joint moved by initial_value holds the new
    position (ctrl = gear * qpos), not the keyframe's."""
    for a in range(m.nu):
        on_joint = int(m.actuator_trntype[a]) == int(mujoco.mjtTrn.mjTRN_JOINT) and int(m.actuator_trnid[a, 0]) == joint.id
        if on_joint and _actuator_kind(m, a) is InterfaceKind.POSITION:
            start.ctrl[a] = float(m.actuator_gear[a, 0]) * start.qpos[joint.qposadr]


def _keyframe_index(asked: str | int, names: list[str]) -> int | None:
    if isinstance(asked, int) or (isinstance(asked, str) and asked.strip().isdigit() and asked not in names):
        k = int(asked)
        return k if 0 <= k < len(names) else None
    return names.index(asked) if asked in names else None


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


def initial_command(spec: RobotSpec, qpos: np.ndarray | None = None) -> np.ndarray:
    """The command each interface starts with, holding the initial state: the keyframe's ctrl
    where it gives one (direct interfaces); else a position interface holds its actuator's
    initial length (its joint's position, or a tendon's length), a PID position interface its
    joint's initial position; velocity and effort start at 0. `qpos` (nq,): a start pose other
    than the initial state's (a randomized one), held the same way."""
    m = spec.mjmodel
    d = mujoco.MjData(m)
    initial = spec.initial if qpos is None else dataclasses.replace(spec.initial, qpos=np.asarray(qpos, np.float64))
    initial.apply(m, d)
    commands = spec.commands if spec.actuator_commands is None else spec.actuator_commands
    out = np.zeros(len(commands))
    for c, cmd in enumerate(commands):
        if cmd.mode is CommandMode.POSITION_PID:
            out[c] = initial.qpos[cmd.qposadr]
        elif cmd.mode is not CommandMode.DIRECT:
            continue
        elif spec.initial.gives_ctrl(cmd.actuator_id):
            out[c] = (spec.initial.ctrl[cmd.actuator_id] - cmd.offset) / cmd.scale
        elif cmd.kind is InterfaceKind.POSITION:
            # the ctrl at which a position servo pushes neither way: gain * ctrl + bias1 * length = 0
            a = cmd.actuator_id
            gain, bias = float(m.actuator_gainprm[a, 0]), float(m.actuator_biasprm[a, 1])
            ctrl = -bias * float(d.actuator_length[a]) / gain if gain else 0.0
            out[c] = (ctrl - cmd.offset) / cmd.scale
    if spec.actuator_commands is None:
        return out
    # through the transmissions: a joint's position holds its actuators', the rest start at 0
    inner = {cmd.name: out[c] for c, cmd in enumerate(commands)}
    joint_side = np.zeros(len(spec.commands))
    by_joint = {j: (t, k) for t in spec.transmissions for k, j in enumerate(t.joints)}
    for c, cmd in enumerate(spec.commands):
        if cmd.mode is not CommandMode.TRANSMITTED:
            joint_side[c] = inner[cmd.name]
        elif cmd.kind is InterfaceKind.POSITION:
            t, k = by_joint[cmd.joint]
            iname = cmd.name.rsplit("/", 1)[1]
            a, b = t.joint_from_actuator(cmd.kind)
            joint_side[c] = (a @ np.array([inner[f"{x}/{iname}"] for x in t.actuators]) + b)[k]
    return joint_side
