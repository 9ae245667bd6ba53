"""The robot model: MJCF loading, the ros2_control block, interface discovery.

`load(model)` turns a model name from `models/` or a path to an MJCF file into a
`RobotSpec`: the compiled `mujoco.MjModel` plus everything batchsim exposes of it.

    spec.py          the data: RobotSpec and what it holds (interfaces, sensors, initial state)
    mjcf.py          loading: shipped models, files, strings, the mujoco.ros2 extension block
    ros2_control.py  the <ros2_control> block: narrowing, initial values
    interfaces.py    discovery: joints, actuators and sensors as ros2_control interfaces
"""

from __future__ import annotations

from batchsim.model.interfaces import floating_base, initial_command
from batchsim.model.mjcf import load, load_string, model_names, model_path
from batchsim.model.spec import (
    ROS2_PLUGIN,
    ROS2_PLUGIN_KEYS,
    CommandInterface,
    FloatingBase,
    InitialState,
    InterfaceKind,
    Joint,
    ModelError,
    RobotSpec,
    RosPluginConfig,
    Sensor,
    StateColumn,
)

__all__ = [
    "ROS2_PLUGIN",
    "ROS2_PLUGIN_KEYS",
    "CommandInterface",
    "FloatingBase",
    "InitialState",
    "InterfaceKind",
    "Joint",
    "ModelError",
    "RobotSpec",
    "RosPluginConfig",
    "Sensor",
    "StateColumn",
    "floating_base",
    "initial_command",
    "load",
    "load_string",
    "model_names",
    "model_path",
]
