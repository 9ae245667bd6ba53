"""Each robot of a world of several (batchsim.fleet) its own controllers, from its own controller_manager YAML.

A robot's YAML names its joints and sensors as the robot alone does (`joint1`, not
`arm_a/joint1`): its controllers are built against `robot_view(world, robot)` (batchsim.fleet.view), the world's
spec in which that robot's own interfaces, joints and sensors carry their local names and
every other robot's keep their prefix. So each controller resolves the robot's names to the
world's columns (the state and command lists keep the world's order), and a name of another
robot's can never be taken for its own.

The controllers of all robots then run in one ControllerManager over the world, each named
`<robot>/<controller>` (its topics land under the robot's namespace: `<robot>/arm_controller/
joint_trajectory`) and claiming the world's names of its interfaces, so two robots' switches
never touch each other's. The bridge serves one controller_manager per robot from it
(`robot_of_controller`).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from batchsim.controllers.base import Controller, Params
from batchsim.controllers.config import CONTROLLER_TYPES, ManagerConfig, default_controllers, parse
from batchsim.controllers.manager import ControllerManager
from batchsim.fleet.view import robot_view
from batchsim.model.mjcf import model_names
from batchsim.model.params import ParamsError, read_yaml
from batchsim.model.spec import RobotPart, RobotSpec
from batchsim.types import ConfigurationError


def robot_controllers_file(robot: RobotPart) -> Path | None:
    """The robot's controllers YAML: its fleet entry's, else a shipped model's default; None: none."""
    if robot.controllers is not None:
        return None if str(robot.controllers).lower() == "none" else robot.controllers
    if robot.model in model_names():
        return default_controllers(robot.model)
    return None


def load_fleet_controllers(world: RobotSpec, nworld: int) -> ControllerManager | None:
    """Every robot's controllers (its fleet entry's YAML, else its shipped model's default) in
    one manager over `nworld` worlds of `world`; None where no robot has any.

    Raises:
      ConfigurationError: a YAML that does not fit its robot, naming the file, the robot and the key.
    """
    controllers = []
    warnings: list[str] = []
    rates: dict[float, str] = {}
    sources = []
    for robot in world.robots:
        source = robot_controllers_file(robot)
        if source is None:
            continue
        _check_namespaces(source, robot, world)
        config = parse(source)
        sources.append(config.source)
        if config.update_rate is not None:
            rates.setdefault(config.update_rate, robot.name)
        warnings += [f"{robot.name}: {w}" for w in config.warnings]
        controllers += _build(config, robot, robot_view(world, robot), nworld, warnings)
    if not controllers:
        return None
    update_rate = max(rates) if rates else None
    for rate, name in rates.items():
        if rate != update_rate:
            warnings.append(
                f"{name}: controller_manager update_rate {rate:g} Hz: its controllers update at the world's "
                f"{update_rate:g} Hz (the fastest robot's)"
            )
    return ControllerManager(
        controllers,
        update_rate=update_rate,
        source=", ".join(sources),
        warnings=warnings,
        spec=world,
        types=CONTROLLER_TYPES,
    )


def _check_namespaces(source: Path, robot: RobotPart, world: RobotSpec) -> None:
    """A robot's YAML whose nodes are namespaced (`/amr_1/controller_manager:`, as multi-robot
    launch files write them) must name this robot: another robot's, or one not in the world, is
    refused naming the key, so a file meant for amr_2 never configures amr_1 unnoticed."""
    try:
        doc = read_yaml(source)
    except ParamsError as e:
        raise ConfigurationError(str(e)) from None
    if not isinstance(doc, Mapping):
        return  # parse() names what is wrong with it
    for key in doc:
        tokens = [t for t in str(key).strip("/").split("/")[:-1] if t and t != "**"]
        if tokens and tokens[-1] != robot.name:
            names = ", ".join(r.name for r in world.robots)
            other = "another robot's" if tokens[-1] in {r.name for r in world.robots} else "no robot of the world"
            raise ConfigurationError(
                f"{source}: {key}: names the namespace {'/'.join(tokens)!r} ({other}), but the file is robot "
                f"{robot.name}'s controllers (robots: {names})"
            )


def _build(
    config: ManagerConfig, robot: RobotPart, view: RobotSpec, nworld: int, warnings: list[str]
) -> list[Controller]:
    out = []
    for c in config.controllers:
        params = Params(c.params, where=f"{config.source} (robot {robot.name})", controller=c.name)
        try:
            controller = CONTROLLER_TYPES[c.type](robot.prefix + c.name, params, view, nworld)
        except ConfigurationError as e:
            raise ConfigurationError(str(e).replace("the model has", f"robot {robot.name} has")) from None
        warnings += params.warnings
        for key in params.unused(controller.ACCEPTED):
            warnings.append(f"{config.source}: controller {c.name!r} of {robot.name}: {key}: ignored: not a parameter of {c.type}")
        # what it claims and reads, by the world's names: the manager and the bridge see those
        controller.command_interfaces = [robot.prefix + n for n in controller.command_interfaces]
        controller.state_interfaces = [robot.prefix + n for n in controller.state_interfaces]
        controller.namespace = robot.prefix
        controller.name_frames(robot.prefix)  # its frames are the robot's: `<ns>/<robot>/<frame>`
        out.append(controller)
    return out


def robot_of_controller(world: RobotSpec, name: str) -> tuple[RobotPart | None, str]:
    """The robot a controller of a fleet's manager belongs to, and its name there."""
    for robot in world.robots:
        if name.startswith(robot.prefix):
            return robot, robot.local(name)
    return None, name
