"""A world of several robots: each robot loaded alone (its description, keyframe, PIDs, mimic
joints and transmissions as for a one-robot world), then attached with MuJoCo's `MjSpec.attach`
under the prefix `<robot>/` at its pose, into the environment's MjSpec, and compiled once.

The world's RobotSpec is each robot's spec with every name prefixed and every address moved by
where that robot's block landed in the compiled world (attach keeps a child's joints,
actuators and sensors contiguous and in their order): nothing is discovered twice, so a robot
behaves in the world exactly as it does alone, and `RobotSpec.robots` says which columns,
sensors and bodies are whose.

What a robot's file holds beside the robot (a Menagerie scene's floor and lights, the rover's
walls) is left out of the world: a robot is the bodies of its file that move (a tree holding
a joint); the environment comes from the fleet file.
"""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np

from batchsim.fleet.file import FleetError, FleetFile, RobotEntry
from batchsim.fleet.sensors import check as check_sensors
from batchsim.fleet.sensors import robot_sensors
from batchsim.model.lidars import LidarElement, PluginLidar, SensorDeclarations
from batchsim.model.mjcf import load_with_mjspec
from batchsim.model.spec import (
    CommandInterface,
    FloatingBase,
    InitialState,
    Joint,
    MimicCommand,
    ModelError,
    RobotPart,
    RobotSpec,
    Sensor,
    StateColumn,
    Transmission,
)
from batchsim.types import StateSource
from batchsim.variation.spec import Placement

#: the MjSpec option fields a world shares: each robot's are set to the world's before attach
_OPTION_FIELDS = (
    "timestep", "integrator", "cone", "jacobian", "solver", "iterations", "tolerance", "ls_iterations",
    "ls_tolerance", "noslip_iterations", "noslip_tolerance", "ccd_iterations", "ccd_tolerance", "impratio",
    "gravity", "wind", "magnetic", "density", "viscosity", "o_margin", "o_solref", "o_solimp", "o_friction",
    "disableflags", "enableflags", "disableactuator", "sdf_initpoints", "sdf_iterations",
)  # fmt: skip


#: the world of a fleet file without `environment:`: a floor and a light, as Menagerie's scenes have
_DEFAULT_ENVIRONMENT = """<mujoco model="fleet">
  <asset>
    <texture name="floor" type="2d" builtin="checker" width="300" height="300" rgb1="0.2 0.3 0.4" rgb2="0.1 0.2 0.3"/>
    <material name="floor" texture="floor" texuniform="true" texrepeat="5 5" reflectance="0.1"/>
  </asset>
  <worldbody>
    <light name="sun" pos="0 0 5" dir="0 0 -1" directional="true"/>
    <geom name="floor" type="plane" size="0 0 0.05" material="floor"/>
  </worldbody>
</mujoco>
"""


@dataclasses.dataclass(frozen=True)
class _Offsets:
    """Where a robot's block starts in the world's model, per address space."""

    joint: int
    qpos: int
    dof: int
    actuator: int
    sensor: int  # sensordata address
    body: int
    nbody: int

    def of(self, source: StateSource, index: int) -> int:
        """A state column's index in the world's `source` field."""
        return index + {
            StateSource.QPOS: self.qpos,
            StateSource.QVEL: self.dof,
            StateSource.QFRC_ACTUATOR: self.dof,
            StateSource.SENSORDATA: self.sensor,
        }[source]


def compose(fleet: FleetFile) -> RobotSpec:
    """The RobotSpec of one world holding every robot of `fleet` (names prefixed `<robot>/`).

    Raises:
      FleetError: a robot whose model cannot be loaded (naming the robot's key), an environment
        MuJoCo rejects, robots a grid places into each other, a robot's sensors file that
        names what the robot lacks or asks for a world's one setting another robot's file
        sets otherwise (batchsim.fleet.sensors).
    """
    world = _environment(fleet)
    loaded: list[tuple[RobotEntry, RobotSpec, int]] = []
    warnings: list[str] = []
    for k, entry in enumerate(fleet.robots):
        try:
            spec, mjspec = load_with_mjspec(entry.model, ros2_control=entry.ros2_control, keyframe=entry.keyframe)
        except ModelError as e:
            raise FleetError(f"{fleet.where}: {entry.key} ({entry.name}): {e}") from None
        nbody = _keep_robot(mjspec)
        lost = _lost(mjspec, spec.mjmodel)
        if lost:
            raise FleetError(
                f"{fleet.where}: {entry.key} ({entry.name}): its {', '.join(lost)} refer to bodies or sites of "
                f"{entry.model} that hold no joint, which a fleet leaves out with the file's scene: give the robot "
                "a file of its own bodies, or put those elements on its moving bodies"
            )
        if k == 0 and fleet.environment is None:
            _copy_options(mjspec, world)  # an empty world steps as its first robot does
        differ = _copy_options(world, mjspec)
        _copy_visual(world, mjspec)
        if differ:
            warnings.append(
                f"{entry.name}: its option {', '.join(differ)} {'differs' if len(differ) == 1 else 'differ'} from the "
                "world's, which it steps with"
            )
        if spec.ros is not None:
            warnings.append(f"{entry.name}: its mujoco.ros2 block is not used in a fleet (the fleet names its topics)")
        yaw = entry.pose[3]
        frame = world.worldbody.add_frame(
            pos=entry.pose[:3], quat=[math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
        )
        world.attach(mjspec, prefix=entry.name + "/", frame=frame)
        loaded.append((entry, spec, nbody))
    try:
        m = world.compile()
    except ValueError as e:
        raise FleetError(f"{fleet.where}: MuJoCo cannot compile the world: {_one_line(str(e))}") from None
    spec = _world_spec(fleet, m, world.to_xml(), loaded, warnings)
    spec.sensor_config = check_sensors(spec, fleet.robots, fleet.where)  # each robot's own file, in world names
    return spec


def _environment(fleet: FleetFile) -> mujoco.MjSpec:
    if fleet.environment is None:
        world = mujoco.MjSpec.from_string(_DEFAULT_ENVIRONMENT)
    else:
        try:
            world = mujoco.MjSpec.from_file(str(fleet.environment))
        except ValueError as e:
            raise FleetError(f"{fleet.where}: environment {fleet.environment}: {_one_line(str(e))}") from None
    world.modelname = fleet.name
    # physics options are made equal before attach (and differences said once, per robot);
    # what else differs (a renderer's zfar) keeps the world's value without a warning per robot
    world.compiler.conflict = mujoco.mjtConflict.mjCONFLICT_MERGE
    return world


def _keep_robot(mjspec: mujoco.MjSpec) -> int:
    """Leave the robot's own bodies in its MjSpec (the worldbody's children whose tree holds a
    joint), deleting its scene: the worldbody's geoms, sites, cameras, lights and static bodies.
    Returns how many bodies remain (the world body not counted). A file with no moving body is
    a static robot and kept whole."""
    top = list(mjspec.worldbody.bodies)
    moving = [b for b in top if _holds_joint(b)]
    if not moving:
        return len(mjspec.bodies) - 1
    for b in top:
        if not _holds_joint(b):
            mjspec.delete(b)
    for kind in ("geoms", "sites", "cameras", "lights"):
        for element in list(getattr(mjspec.worldbody, kind)):
            mjspec.delete(element)
    return len(mjspec.bodies) - 1


def _lost(mjspec: mujoco.MjSpec, alone: mujoco.MjModel) -> list[str]:
    """What the robot's file loses with its scene (its sensors, actuators, equalities or
    tendons on a static body or site, mocap bodies), as "2 sensors", by compiling what is kept."""
    kept = mjspec.copy().compile()
    counts = (("sensor", "nsensor"), ("actuator", "nu"), ("equality", "neq"), ("tendon", "ntendon"), ("joint", "njnt"))
    return [
        f"{getattr(alone, n) - getattr(kept, n)} {what}{'s' if getattr(alone, n) - getattr(kept, n) > 1 else ''}"
        for what, n in counts
        if getattr(kept, n) < getattr(alone, n)
    ]


def _holds_joint(body: mujoco.MjsBody) -> bool:
    return bool(body.joints) or any(_holds_joint(child) for child in body.bodies)


def _copy_options(source: mujoco.MjSpec, target: mujoco.MjSpec) -> list[str]:
    """Set target's physics options to source's; the names of those that differed."""
    differ = []
    for field in _OPTION_FIELDS:
        value, was = getattr(source.option, field), getattr(target.option, field)
        if not np.array_equal(np.asarray(value), np.asarray(was)):
            differ.append(field)
            setattr(target.option, field, value)
    return differ


def _copy_visual(source: mujoco.MjSpec, target: mujoco.MjSpec) -> None:
    """Set target's visual settings (headlight, map, quality, ...) and statistic to source's:
    the world is drawn one way, whatever each robot's file chose."""
    for group in ("global_", "headlight", "map", "quality", "rgba", "scale"):
        src, dst = getattr(source.visual, group), getattr(target.visual, group)
        for field in dir(src):
            if not field.startswith("_"):
                try:
                    setattr(dst, field, getattr(src, field))
                except (AttributeError, TypeError):
                    pass  # a read-only or method attribute
    for field in ("center", "extent", "meaninertia", "meanmass", "meansize"):
        setattr(target.stat, field, getattr(source.stat, field))


def _world_spec(
    fleet: FleetFile,
    m: mujoco.MjModel,
    xml: str,
    loaded: list[tuple[RobotEntry, RobotSpec, int]],
    warnings: list[str],
) -> RobotSpec:
    joints: list[Joint] = []
    state: list[StateColumn] = []
    commands: list[CommandInterface] = []
    actuator_commands: list[CommandInterface] = []
    sensors: list[Sensor] = []
    mimics: list[MimicCommand] = []
    transmissions: list[Transmission] = []
    actuator_joints: list[tuple[str, int, int]] = []
    problems: list[str] = []
    declarations = SensorDeclarations(where=fleet.where)
    parts: list[RobotPart] = []
    start = InitialState.of_model(m)
    given = np.zeros(m.nu, bool)
    labels = []
    n_actuator = m.nu - sum(spec.mjmodel.nu for _, spec, _ in loaded)  # the environment's come first
    n_sensor = m.nsensor - sum(spec.mjmodel.nsensor for _, spec, _ in loaded)
    for entry, spec, nbody in loaded:
        off = _offsets(m, entry, spec, nbody, n_actuator, n_sensor)
        n_actuator += spec.mjmodel.nu
        n_sensor += spec.mjmodel.nsensor
        p = entry.name + "/"
        first_state, first_command = len(state), len(commands)
        joints += [Joint(p + j.name, j.id + off.joint, j.qposadr + off.qpos, j.dofadr + off.dof) for j in spec.joints]
        state += [
            dataclasses.replace(c, name=p + c.name, index=off.of(c.source, c.index)) for c in spec.state
        ]
        commands += [_command(c, p, off) for c in spec.commands]
        actuator_commands += [_command(c, p, off) for c in (spec.actuator_commands or spec.commands)]
        sensors += [
            dataclasses.replace(
                s, name=p + s.name, adr=s.adr + off.sensor, objname=p + s.objname if s.objname else s.objname
            )
            for s in spec.sensors
        ]
        mimics += [
            dataclasses.replace(
                x, joint=p + x.joint, source=p + x.source, actuator=p + x.actuator, actuator_id=x.actuator_id + off.actuator
            )
            for x in spec.mimics
        ]
        transmissions += [
            dataclasses.replace(
                t, name=p + t.name, joints=tuple(p + j for j in t.joints), actuators=tuple(p + a for a in t.actuators)
            )
            for t in spec.transmissions
        ]
        actuator_joints += [
            (p + name, q + off.qpos if q >= 0 else q, d + off.dof if d >= 0 else d)
            for name, q, d in spec.actuator_joints
        ]
        problems += [f"{entry.name}: {x}" for x in spec.problems]
        warnings += [f"{entry.name}: {x}" for x in spec.warnings]
        declarations = declarations.merged(_declarations(spec.sensor_declarations, p))
        _place_initial(m, start, given, spec, off, entry.pose)
        labels.append(f"{entry.name}: {spec.initial.source}")
        base = spec.floating_base
        parts.append(
            RobotPart(
                name=entry.name,
                model=entry.model,
                state=np.arange(first_state, len(state)),
                commands=np.arange(first_command, len(commands)),
                sensors=tuple(p + s.name for s in spec.sensors),
                joints=tuple(p + j.name for j in spec.joints),
                bodies=(off.body, off.nbody),
                qpos=(off.qpos, spec.mjmodel.nq),
                dofs=(off.dof, spec.mjmodel.nv),
                actuators=(off.actuator, spec.mjmodel.nu),
                floating_base=None
                if base is None
                else FloatingBase(p + base.joint, p + base.body, base.qposadr + off.qpos, base.dofadr + off.dof),
                pose=entry.pose,
                controllers=entry.controllers,
                sensor_config=entry.sensors,
                sensor_settings=robot_sensors(fleet.where, entry, spec, m),
                spec=spec,
            )
        )
    start.ctrl_given = given
    start.label = "; ".join(labels)
    placements = _placements(fleet, parts)
    transmitted = any(spec.actuator_commands is not None for _, spec, _ in loaded)
    world = RobotSpec(
        name=fleet.name,
        path=fleet.path,
        mjmodel=m,
        xml=xml,
        joints=joints,
        state=state,
        commands=commands,
        sensors=sensors,
        floating_base=None,  # each robot's own is its RobotPart's
        initial=start,
        keyframes=[m.key(k).name for k in range(m.nkey)],
        mimics=mimics,
        problems=problems,
        sensor_declarations=declarations,
        warnings=warnings,
        transmissions=transmissions,
        actuator_commands=actuator_commands if transmitted else None,
        actuator_joints=actuator_joints,
        robots=parts,
        placements=placements,
    )
    return world


def _placements(fleet: FleetFile, parts: list[RobotPart]) -> tuple[Placement, ...]:
    """The fleet's random placement rules, each over the free joints of the robots it places."""
    rules: dict[str, list[int]] = {}
    for entry, part in zip(fleet.robots, parts, strict=True):
        if entry.random is None:
            continue
        if part.floating_base is None:
            raise FleetError(
                f"{fleet.where}: {entry.random.key}: places a robot by its free joint, and {entry.name} ({entry.model}) "
                "has a fixed base: give it a pose or a grid"
            )
        rules.setdefault(entry.random.key, []).append(part.floating_base.qposadr)
    by_key = {e.random.key: e.random for e in fleet.robots if e.random is not None}
    return tuple(
        Placement(tuple(adr), by_key[key].area, by_key[key].yaw, by_key[key].min_distance, f"{fleet.where}: {key}")
        for key, adr in rules.items()
    )


def _offsets(
    m: mujoco.MjModel, entry: RobotEntry, spec: RobotSpec, nbody: int, first_actuator: int, first_sensor: int
) -> _Offsets:
    """Where `spec`'s robot landed in the world's model, checked name by name."""
    r = spec.mjmodel
    p = entry.name + "/"
    body = _first_body(m, r, p, entry)
    joint = next((j for j in range(m.njnt) if body <= int(m.jnt_bodyid[j]) < body + nbody), 0)
    off = _Offsets(
        joint=joint,
        qpos=int(m.jnt_qposadr[joint]) if r.njnt else 0,
        dof=int(m.jnt_dofadr[joint]) if r.njnt else 0,
        actuator=first_actuator,
        sensor=int(m.sensor_adr[first_sensor]) if r.nsensor else 0,
        body=body,
        nbody=nbody,
    )
    for kind, n, start in (
        (mujoco.mjtObj.mjOBJ_JOINT, r.njnt, off.joint),
        (mujoco.mjtObj.mjOBJ_ACTUATOR, r.nu, off.actuator),
        (mujoco.mjtObj.mjOBJ_SENSOR, r.nsensor, first_sensor),
    ):
        for i in range(n):
            name = mujoco.mj_id2name(r, kind, i)
            if name and mujoco.mj_id2name(m, kind, start + i) != p + name:
                raise FleetError(
                    f"{entry.key} ({entry.name}): its {kind.name.removeprefix('mjOBJ_').lower()} {name!r} is not "
                    "where attach put the robot's others: a file whose robot refers to its scene's elements"
                )
    return off


def _first_body(m: mujoco.MjModel, r: mujoco.MjModel, prefix: str, entry: RobotEntry) -> int:
    """The world's id of the robot's first body (its block of bodies follows it)."""
    for b in range(1, m.nbody):
        if mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) and m.body(b).name.startswith(prefix):
            return b
    raise FleetError(f"{entry.key} ({entry.name}): its model {entry.model} has no named body to attach")


def _command(c: CommandInterface, p: str, off: _Offsets) -> CommandInterface:
    return dataclasses.replace(
        c,
        name=p + c.name,
        actuator=p + c.actuator,
        actuator_id=c.actuator_id + off.actuator,
        joint=p + c.joint if c.joint else c.joint,
        qposadr=c.qposadr + off.qpos if c.qposadr >= 0 else c.qposadr,
        dofadr=c.dofadr + off.dof if c.dofadr >= 0 else c.dofadr,
    )


def _declarations(d: SensorDeclarations, p: str) -> SensorDeclarations:
    """A robot's lidar declarations with its sites and sensors named as in the world."""
    return SensorDeclarations(
        tuple(
            dataclasses.replace(e, ref_site=p + e.ref_site, sensor_name=p + e.sensor_name)
            for e in d.lidar_elements
            if isinstance(e, LidarElement)
        ),
        tuple(
            dataclasses.replace(x, name=p + x.name, site=p + x.site) for x in d.plugin_lidars if isinstance(x, PluginLidar)
        ),
        tuple((p + name, params) for name, params in d.sensor_params),
        d.rates,
        d.where,
    )


def _place_initial(
    m: mujoco.MjModel,
    start: InitialState,
    given: np.ndarray,
    spec: RobotSpec,
    off: _Offsets,
    pose: tuple[float, float, float, float],
) -> None:
    """The robot's own start (its keyframe, initial_value) into the world's, its free joints
    carried to its pose: a keyframe holds a free joint's pose in the robot file's world frame."""
    r, ini = spec.mjmodel, spec.initial
    assert ini is not None
    start.qpos[off.qpos : off.qpos + r.nq] = ini.qpos
    start.qvel[off.dof : off.dof + r.nv] = ini.qvel
    start.ctrl[off.actuator : off.actuator + r.nu] = ini.ctrl
    given[off.actuator : off.actuator + r.nu] = [ini.gives_ctrl(a) for a in range(r.nu)]
    for a in range(r.nu):
        adr = int(r.actuator_actadr[a])
        if adr >= 0:
            world_adr = int(m.actuator_actadr[off.actuator + a])
            n = int(r.actuator_actnum[a])
            start.act[world_adr : world_adr + n] = ini.act[adr : adr + n]
    yaw = pose[3]
    c, s = math.cos(yaw), math.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    q_yaw = np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])
    for j in range(r.njnt):
        if int(r.jnt_type[j]) != int(mujoco.mjtJoint.mjJNT_FREE):
            continue
        q, v = off.qpos + int(r.jnt_qposadr[j]), off.dof + int(r.jnt_dofadr[j])
        start.qpos[q : q + 3] = np.asarray(pose[:3]) + rot @ ini.qpos[int(r.jnt_qposadr[j]) :][:3]
        quat = np.empty(4)
        mujoco.mju_mulQuat(quat, q_yaw, ini.qpos[int(r.jnt_qposadr[j]) + 3 :][:4])
        start.qpos[q + 3 : q + 7] = quat
        start.qvel[v : v + 3] = rot @ ini.qvel[int(r.jnt_dofadr[j]) :][:3]  # linear: world frame
    if ini.initial_values:
        start.initial_values = True


def _one_line(message: str) -> str:
    parts = [p.strip() for p in message.strip().splitlines() if p.strip()]
    return "; ".join(parts) or "MuJoCo could not compile it"


def robot_of_body(spec: RobotSpec, body: int) -> RobotPart | None:
    """The robot a body of the world's model belongs to, or None (the environment's)."""
    for r in spec.robots:
        first, n = r.bodies
        if first <= body < first + n:
            return r
    return None


def overlaps(spec: RobotSpec) -> list[tuple[str, str, float, str, str]]:
    """Robots that touch each other at the world's start: (robot, robot, penetration depth in
    metres, geom, geom) per pair of robots, the deepest contact of each pair, deepest first."""
    m = spec.mjmodel
    d = mujoco.MjData(m)
    assert spec.initial is not None
    spec.initial.apply(m, d)
    deepest: dict[tuple[str, str], tuple[float, str, str]] = {}
    for i in range(d.ncon):
        c = d.contact[i]
        if c.dist >= 0:
            continue
        a = robot_of_body(spec, int(m.geom_bodyid[c.geom1]))
        b = robot_of_body(spec, int(m.geom_bodyid[c.geom2]))
        if a is None or b is None or a is b:
            continue
        pair = tuple(sorted((a.name, b.name)))
        depth = -float(c.dist)
        if depth > deepest.get(pair, (0.0, "", ""))[0]:
            deepest[pair] = (depth, m.geom(c.geom1).name or f"geom{c.geom1}", m.geom(c.geom2).name or f"geom{c.geom2}")
    found = [(a, b, depth, g1, g2) for (a, b), (depth, g1, g2) in deepest.items()]
    return sorted(found, key=lambda x: -x[2])
