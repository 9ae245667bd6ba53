"""Reading a ros2_control controller_manager YAML, the same file a robot already has.

    controller_manager:
      ros__parameters:
        update_rate: 100  # Hz
        joint_state_broadcaster:
          type: joint_state_broadcaster/JointStateBroadcaster
        arm_controller:
          type: joint_trajectory_controller/JointTrajectoryController

    arm_controller:
      ros__parameters:
        joints: [joint1, joint2]
        command_interfaces: [position]
        state_interfaces: [position, velocity]

Both layouts ros2_control accepts load: the `type` in the controller_manager's block (above)
or in each controller's own `ros__parameters` (as mujoco_ros2_control's demos write it):

    controller_manager:
      ros__parameters:
        update_rate: 100
    position_controller:
      ros__parameters:
        type: forward_command_controller/ForwardCommandController
        joints: [joint1, joint2]

Node keys may carry a namespace or wildcard (`/controller_manager`, `/**/arm_controller`).
Nested parameters (`linear: {x: {max_velocity: 1.0}}`) and dotted ones
(`linear.x.max_velocity: 1.0`) mean the same; a key written twice in one mapping is merged,
as ROS merges it. Every mistake the model can reveal is a ConfigurationError of one line
naming the file, the controller and the key; a declared controller never goes missing: an
unknown type is an error, and a file that declares no controller at all says so in a warning.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from batchsim.controllers.base import Params
from batchsim.controllers.manager import ControllerManager
from batchsim.controllers.types import CONTROLLER_TYPES
from batchsim.model import RobotSpec
from batchsim.model.params import ParamsError, load_yaml, read_text
from batchsim.types import ConfigurationError

# keys of a controller's entry in the controller_manager block besides `type`
_MANAGER_ENTRY_KEYS = ("type", "params_file", "fallback_controllers")


@dataclasses.dataclass
class ControllerConfig:
    """One controller as the YAML declares it."""

    name: str
    type: str
    params: dict[str, Any]


@dataclasses.dataclass
class ManagerConfig:
    """A parsed controller_manager YAML, not yet checked against a model."""

    source: str
    update_rate: float | None
    controllers: list[ControllerConfig]
    warnings: list[str]


def default_controllers(model_name: str) -> Path | None:
    """The default controllers YAML shipped beside a shipped model (models/<name>.yaml), if any."""
    path = importlib.resources.files("batchsim.models") / f"{model_name}.yaml"
    return Path(str(path)) if path.is_file() else None


def _node_name(key: Any) -> str:
    """`/ns/controller_manager`, `/**/arm_controller` -> the node's own name."""
    return str(key).rstrip("/").rsplit("/", 1)[-1]


def _flatten(values: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in values.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping) and v:
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def parse(source: str | Path | Mapping[str, Any], *, name: str | None = None) -> ManagerConfig:
    """Parse a controller_manager YAML: a file path, YAML text, or an already-loaded mapping."""
    if isinstance(source, Mapping):
        where, doc = name or "controllers", source
    else:
        text = str(source)
        if isinstance(source, Path) or ("\n" not in text and not text.lstrip().startswith("{")):
            path = Path(text).expanduser()
            where = name or str(source)
            try:
                text = read_text(path, where)
            except ParamsError as e:
                raise ConfigurationError(str(e)) from None
        else:
            where = name or "controllers"
        try:
            doc = load_yaml(text, where)
        except ParamsError as e:
            raise ConfigurationError(str(e)) from None
    if not isinstance(doc, Mapping):
        raise ConfigurationError(
            f"{where}: expected a mapping with a controller_manager: ros__parameters: block"
        )

    nodes: dict[str, Mapping[str, Any]] = {}
    for key, value in doc.items():
        node = _node_name(key)
        if node == "**" and isinstance(value, Mapping):  # `/**: ros__parameters:` applies to every node
            continue
        params = value.get("ros__parameters") if isinstance(value, Mapping) else None
        if not isinstance(params, Mapping):
            raise ConfigurationError(f"{where}: {key}: expected a ros__parameters: block")
        nodes[node] = params
    manager = nodes.pop("controller_manager", None)
    if manager is None:
        raise ConfigurationError(f"{where}: no controller_manager: ros__parameters: block")

    update_rate = None
    if "update_rate" in manager:
        rate = manager["update_rate"]
        if isinstance(rate, bool) or not isinstance(rate, int | float) or not rate > 0:
            raise ConfigurationError(
                f"{where}: controller_manager: update_rate: must be a number > 0, got {rate!r}"
            )
        update_rate = float(rate)

    controllers: list[ControllerConfig] = []
    warnings: list[str] = []
    declared: dict[str, Mapping[str, Any]] = {}  # name -> its controller_manager entry
    for cname, entry in manager.items():
        if isinstance(entry, Mapping):  # update_rate and the manager's own parameters are not
            declared[str(cname)] = entry
    for node, params in nodes.items():  # the other layout: `type` in the controller's own block
        if node not in declared and "type" in params:
            declared[node] = {"type": params["type"]}
    for cname, entry in declared.items():
        if "type" not in entry:
            raise ConfigurationError(f"{where}: controller {cname!r}: type: missing")
        ctype = entry["type"]
        if not isinstance(ctype, str):
            raise ConfigurationError(f"{where}: controller {cname!r}: type: must be a plugin name, got {ctype!r}")
        if ctype not in CONTROLLER_TYPES:
            raise ConfigurationError(
                f"{where}: controller {cname!r}: type: unknown type {ctype!r} "
                f"(supported: {', '.join(CONTROLLER_TYPES)})"
            )
        own = nodes.pop(cname, {})
        if "type" in own and own["type"] != ctype:
            raise ConfigurationError(
                f"{where}: controller {cname!r}: type: {own['type']!r} in its own block but {ctype!r} "
                "in controller_manager's"
            )
        params = _flatten({k: v for k, v in own.items() if k != "type"})
        for k, v in entry.items():
            if k not in _MANAGER_ENTRY_KEYS:
                params.setdefault(k, v)
        controllers.append(ControllerConfig(str(cname), ctype, params))
    for node, params in nodes.items():
        if "pid_gains" in params or any(str(k).startswith("pid_gains.") for k in params):
            warnings.append(
                f"{where}: {node}: pid_gains: ignored: batchsim reads PID gains from the ros2_control "
                "block's pids_config_file"
            )
        else:
            warnings.append(f"{where}: {node}: ignored: no controller of that name and no type")
    if not controllers:
        warnings.append(
            f"{where}: declares no controller (give each a type: in controller_manager's block or its own)"
        )
    return ManagerConfig(where, update_rate, controllers, warnings)


def build(config: ManagerConfig, spec: RobotSpec, nworld: int) -> ControllerManager:
    """The controllers of a parsed YAML for `nworld` worlds of `spec`; ConfigurationError if they don't fit."""
    controllers = []
    warnings = list(config.warnings)
    for c in config.controllers:
        params = Params(c.params, where=config.source, controller=c.name)
        controller = CONTROLLER_TYPES[c.type](c.name, params, spec, nworld)
        controller.name_frames()  # `<ns>/<frame>`, as tf names the world's frames
        warnings += params.warnings
        for key in params.unused(controller.ACCEPTED):
            warnings.append(
                f"{config.source}: controller {c.name!r}: {key}: ignored: not a parameter of {c.type}"
            )
        controllers.append(controller)
    return ControllerManager(
        controllers,
        update_rate=config.update_rate,
        source=config.source,
        warnings=warnings,
        spec=spec,
        types=CONTROLLER_TYPES,
    )


def load_controllers(
    source: str | Path | Mapping[str, Any], spec: RobotSpec, nworld: int, *, name: str | None = None
) -> ControllerManager:
    """Parse a controller_manager YAML and build its controllers for `nworld` worlds of `spec`."""
    return build(parse(source, name=name), spec, nworld)
