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

import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np

from batchsim.model.ros2_control import narrow
from batchsim.model.spec import (
    CommandInterface,
    FloatingBase,
    InitialState,
    InterfaceKind,
    Joint,
    RobotSpec,
    RosPluginConfig,
    Sensor,
    StateColumn,
)

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


def discover(
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
        joints, joint_states, commands, sensors = narrow(
            block, joints, commands, sensors, problems, initial
        )
    start = InitialState.of_model(m)
    if initial:  # a ros2_control initial_value is where the joint starts and resets to; qpos0 stays
        for j in joints:
            if j.name in initial:
                start.qpos[j.qposadr] = initial[j.name]
        start.source = "qpos0 with ros2_control initial_value"

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
        initial=start,
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


def initial_command(spec: RobotSpec) -> np.ndarray:
    """The command each interface starts with: hold the initial pose, zero velocity and effort."""
    m = spec.mjmodel
    out = np.zeros(len(spec.commands))
    for c, cmd in enumerate(spec.commands):
        if cmd.kind is InterfaceKind.POSITION and cmd.joint is not None:
            out[c] = spec.initial.qpos[m.joint(cmd.joint).qposadr[0]]
    return out
