"""A robot's own sensors file in a world of several: the file that robot takes alone
(`batchsim --model rover --sensors amr_sensors.yaml`; cameras, lidars, noise and
mujoco_ros2_control's plugin YAML, batchsim.sensors.config), given under the robot in a fleet
file (`sensors: amr_sensors.yaml`).

Each file is read with `SensorConfig.load`, checked against the robot alone (a name it lacks is
named as the robot names it), then its names are moved under the robot's prefix, as MjSpec
attach named the robot's elements (robot `amr_1`):

    cameras, rangefinder and plugin lidars, dense lidars    front_camera   -> amr_1/front_camera
    a dense lidar's site, the BaseVelocityPlugin's body     lidar          -> amr_1/lidar
    noise patterns (interfaces, sensors, cameras, lidars)   */position     -> amr_1/*/position
    frame names and topics, relative or absolute            cam/rgb        -> amr_1/cam/rgb

so its topics and frames sit under the robot's namespace as they sit under the world's for the
robot alone (`/world_3/amr_1/cam/rgb`, frame `world_3/amr_1/...`), and its noise matches only
that robot's interfaces. Its `camera_resolution` sizes that robot's cameras only.

Some settings are one per world: the noise seed, camera_rate, lidar_rate, and one instance each
of the BaseVelocityPlugin and the ExternalWrenchPlugin. A robot's file that sets one sets it for
the world (a warning names the other robots it reaches); two robots' files that differ there
are refused, naming both (FleetError).

`merged` joins every robot's into the world's one SensorConfig (RobotSpec.sensor_config), and
lays a configuration given for the whole fleet (`--sensors`, `make(sensors=)`, world names)
over it: that one wins where both set a key.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import mujoco

from batchsim.fleet.file import FleetError, RobotEntry
from batchsim.model.lidars import DeclarationError, rangefinder_groups
from batchsim.model.spec import RobotPart, RobotSpec
from batchsim.plugins.base_velocity import BaseVelocity
from batchsim.sensors.config import CameraSettings, SensorConfig, SensorConfigError
from batchsim.sensors.suite import SensorSuite
from batchsim.types import ConfigurationError

#: a camera's and a lidar's settings that name a frame or a topic: under the robot's namespace
_NAMED = ("frame_name", "image_topic", "depth_topic", "info_topic", "topic")
#: the settings a world has one of: (field, what it is, the value that means unset)
_ONE_PER_WORLD = (("seed", "noise seed", 0), ("camera_rate", "camera rate", None), ("lidar_rate", "lidar rate", None))
_PLUGINS = (("base_velocity", "a BaseVelocityPlugin"), ("external_wrench", "an ExternalWrenchPlugin"))


def robot_sensors(where: str, entry: RobotEntry, alone: RobotSpec, world: mujoco.MjModel) -> SensorConfig | None:
    """Robot `entry`'s own sensors file (None without one), checked against the robot alone
    (`alone`) and named as the world `world` names the robot's elements.

    Raises:
      FleetError: one line naming the fleet file, the robot's key, its file and the key at
        fault: an unreadable or malformed file, a name the robot lacks (its own name), a camera
        or site of the robot file's scene, which the fleet leaves out.
    """
    if entry.sensors is None or str(entry.sensors).lower() == "none":
        return None
    at = f"{where}: {label(entry)}"
    try:
        config = SensorConfig.load(Path(entry.sensors))
        SensorSuite.build(alone, 1, config)  # every name the file gives, as the robot alone has it
        if config.base_velocity is not None:
            BaseVelocity(config.base_velocity, alone.mjmodel, 1)
    except (SensorConfigError, ConfigurationError, DeclarationError) as e:
        raise FleetError(f"{at}: {e}") from None
    p = entry.name + "/"
    for name in config.cameras:
        if mujoco.mj_name2id(world, mujoco.mjtObj.mjOBJ_CAMERA, p + name) < 0:
            raise FleetError(
                f"{at}: {config.source}: camera {name!r} is on a body of {entry.model} that holds no joint, which a "
                "fleet leaves out with the file's scene"
            )
    for d in config.dense_lidars:
        if mujoco.mj_name2id(world, mujoco.mjtObj.mjOBJ_SITE, p + d.site) < 0:
            raise FleetError(
                f"{at}: {config.source}: sensors.lidars.{d.name}.site: {d.site!r} is on a body of {entry.model} that "
                "holds no joint, which a fleet leaves out with the file's scene"
            )
    return prefixed(config, p)


def label(entry: RobotEntry) -> str:
    """Where a robot's sensors file is given, for messages: `robots[0].sensors (amr_1)`."""
    return f"{entry.key.partition(' ')[0]}.sensors ({entry.name})"


def prefixed(config: SensorConfig, p: str) -> SensorConfig:
    """`config`, written for a robot alone, with every name under the prefix `p` (`amr_1/`)."""
    bv = config.base_velocity
    return dataclasses.replace(
        config,
        cameras={p + n: _under_prefix(s, p) for n, s in config.cameras.items()},
        rangefinder_lidars={p + n: _under_prefix(s, p) for n, s in config.rangefinder_lidars.items()},
        plugin_lidars={p + n: _under_prefix(s, p) for n, s in config.plugin_lidars.items()},
        dense_lidars=[dataclasses.replace(_under_prefix(d, p), name=p + d.name, site=p + d.site) for d in config.dense_lidars],
        noise={p + pattern: nz for pattern, nz in config.noise.items()},
        base_velocity=None
        if bv is None
        else dataclasses.replace(bv, body=p + bv.body, cmd_vel_topic=p + bv.cmd_vel_topic.lstrip("/")),
        warnings=list(config.warnings),
    )


def _under_prefix(settings: Any, p: str) -> Any:
    """A camera's or lidar's settings with its frame and topics under `p` (absolute ones too:
    the bridge puts those under the world's namespace, `/cam` of world 3 is `/world_3/cam`)."""
    names = {f: p + v.lstrip("/") for f in _NAMED if isinstance(v := getattr(settings, f, None), str)}
    return dataclasses.replace(settings, **names)


def _over(top: Any, below: Any) -> Any:
    """Settings `top` laid over `below` (same class): top's values where it sets them."""
    if below is None:
        return top
    if top is None:
        return below
    return dataclasses.replace(below, **{f.name: v for f in dataclasses.fields(top) if (v := getattr(top, f.name)) is not None})


def merged(
    spec: RobotSpec,
    user: SensorConfig | str | Path | Mapping[str, Any] | None = None,
    labels: Callable[[RobotPart], str] | None = None,
) -> SensorConfig | None:
    """The sensor configuration a system of `spec` takes: its robots' own files (each robot's
    `sensor_settings`) in one, with `user` (world names: a SensorConfig, a file or a mapping)
    laid over it; where no robot has a file, `user`, else `spec.sensor_config` (None: neither).

    Raises:
      FleetError: two robots' files that set a world's one setting differently (the seed, a
        rate, a plugin), naming both files and keys.
      SensorConfigError: a `user` file that cannot be read.
    """
    if user is not None and not isinstance(user, SensorConfig):
        user = SensorConfig.load(user)
    own = [(r, r.sensor_settings) for r in spec.robots if r.sensor_settings is not None]
    if not own:
        return user if user is not None else spec.sensor_config
    where = str(spec.path) if spec.path is not None else "<fleet>"
    named = labels or (lambda r: f"{r.name}.sensors")
    m = spec.mjmodel
    out = SensorConfig(
        source=", ".join([c.source for _, c in own] + ([user.source] if user is not None else [])),
        warnings=[w for _, c in own for w in c.warnings] + (list(user.warnings) if user is not None else []),
    )
    for field, what, unset in _ONE_PER_WORLD:
        given = [(r, c) for r, c in own if getattr(c, field) != unset]
        if user is not None and getattr(user, field) != unset:
            setattr(out, field, getattr(user, field))
        elif given:
            (ra, a), value = given[0], getattr(given[0][1], field)
            other = next(((r, c) for r, c in given if getattr(c, field) != value), None)
            if other is not None:
                rb, b = other
                raise FleetError(
                    f"{where}: {named(ra)}: {a.source} sets {field} {value:g} and {named(rb)}: {b.source} sets {field} "
                    f"{getattr(b, field):g}: a world has one {what}: give both the same (or give it to the whole fleet)"
                )
            setattr(out, field, value)
            setters = {r.name for r, _ in given}
            reached = [r.name for r in spec.robots if r.name not in setters and _takes(m, r, field)]
            if reached:
                out.warnings.append(
                    f"{named(ra)}: {a.source}: {field} {value:g} is the world's (a world has one {what}): "
                    f"{', '.join(reached)} {'takes' if len(reached) == 1 else 'take'} it too"
                )
    for field, kind in _PLUGINS:
        given = [(r, getattr(c, field)) for r, c in own if getattr(c, field) is not None]
        if len(given) > 1:
            (ra, a), (rb, b) = given[:2]
            raise FleetError(
                f"{where}: {named(ra)}: {a.where} and {named(rb)}: {b.where} each ask for {kind}: the system runs "
                "one per world (give it to one robot)"
            )
        mine = given[0][1] if given else None
        if user is not None and getattr(user, field) is not None:
            mine = getattr(user, field)
        elif field == "external_wrench" and mine is not None:
            out.warnings.append(
                f"{named(given[0][0])}: {mine.where}: its service is the world's <ns>/{mine.service}, whose requests "
                f"name bodies as the world does ({given[0][0].prefix}<body>)"
            )
        setattr(out, field, mine)
    sized = user is None or user.camera_resolution is None  # else the whole fleet's size wins over each robot's
    for r, c in own:
        first, n = r.bodies
        if sized and c.camera_resolution is not None:
            width, height = c.camera_resolution
            for cam in range(m.ncam):
                name = m.camera(cam).name
                if name and first <= int(m.cam_bodyid[cam]) < first + n:
                    out.cameras[name] = _over(c.cameras.get(name), CameraSettings(width=width, height=height))
        out.cameras = {**c.cameras, **out.cameras}
        out.rangefinder_lidars.update(c.rangefinder_lidars)
        out.plugin_lidars.update(c.plugin_lidars)
        out.dense_lidars += c.dense_lidars
    noise = {pattern: nz for _, c in own for pattern, nz in c.noise.items()}
    if user is not None:
        out.camera_resolution = user.camera_resolution
        for table in ("cameras", "rangefinder_lidars", "plugin_lidars"):
            mine = getattr(out, table)
            for name, s in getattr(user, table).items():
                mine[name] = _over(s, mine.get(name))
        theirs = {d.name for d in user.dense_lidars}
        out.dense_lidars = [d for d in out.dense_lidars if d.name not in theirs] + list(user.dense_lidars)
        # the first pattern that matches a value gives its noise (batchsim.sensors.suite): the user's first
        noise = {**user.noise, **{p: nz for p, nz in noise.items() if p not in user.noise}}
    out.noise = noise
    return out


def _takes(m: mujoco.MjModel, robot: RobotPart, field: str) -> bool:
    """Whether `robot`'s own sensors would take a world-wide `field` its file does not set: its
    noise the seed, its cameras (in the world `m`) the camera rate, its lidars the lidar rate."""
    if field == "seed":
        return robot.sensor_settings is not None and bool(robot.sensor_settings.noise)
    if field == "camera_rate":
        first, n = robot.bodies
        return any(first <= int(b) < first + n for b in m.cam_bodyid)
    alone = robot.spec
    if alone is None:
        return False
    decl = alone.sensor_declarations
    return bool(rangefinder_groups(alone.mjmodel) or decl.lidar_elements or decl.plugin_lidars)


def check(spec: RobotSpec, entries: Sequence[RobotEntry], where: str) -> SensorConfig | None:
    """The world's configuration from its robots' files (`merged`, messages naming each robot's
    key), resolved against the world's model once, so a fault shows at load, not at configure."""
    keys = {e.name: label(e) for e in entries}
    config = merged(spec, labels=lambda r: keys[r.name])
    if config is not None:
        try:
            SensorSuite.build(spec, 1, config)
        except SensorConfigError as e:
            raise FleetError(f"{where}: the robots' sensors files in the world: {e}") from None
    return config
