"""The robot model: MJCF loading, the ros2_control block, interface discovery.

`load(model)` turns a model name from `models/` or a path to an MJCF file into a
`RobotSpec`: the compiled `mujoco.MjModel` plus everything batchsim exposes of it.

    spec.py          the data: RobotSpec and what it holds (interfaces, sensors, initial state)
    mjcf.py          loading: shipped models, files, strings, the mujoco.ros2 extension block
    description.py   robot descriptions (URDF, xacro, XML): their <ros2_control> blocks as data
    ros2_control.py  what the blocks make of a model: narrowing, actuators by name, PIDs, sensors
    params.py        ROS 2 parameter files (pids_config_file, controllers YAML)
    interfaces.py    discovery: joints, actuators and sensors as ros2_control interfaces; keyframes
    transmissions.py a description's ros2_control <transmission>s
    from_urdf.py     a URDF-only robot compiled to MJCF, as mujoco_ros2_control's tool does
    lidars.py        the lidars an MJCF declares that MuJoCo does not compile
    frames.py        the tf tree: a frame per body, the parent->child transforms
    urdf.py          robot_description from the MJCF
"""

from __future__ import annotations

from batchsim.model.description import Description, read_description
from batchsim.model.interfaces import floating_base, initial_command
from batchsim.model.mjcf import load, load_string, load_with_mjspec, model_names, model_path
from batchsim.model.spec import (
    ROS2_PLUGIN,
    ROS2_PLUGIN_KEYS,
    CommandInterface,
    CommandMode,
    FloatingBase,
    InitialState,
    InterfaceKind,
    Joint,
    MimicCommand,
    ModelError,
    RobotPart,
    RobotSpec,
    RosPluginConfig,
    Sensor,
    StateColumn,
    Transmission,
    TransmissionKind,
)

__all__ = [
    "ROS2_PLUGIN",
    "ROS2_PLUGIN_KEYS",
    "CommandInterface",
    "CommandMode",
    "Description",
    "FloatingBase",
    "InitialState",
    "InterfaceKind",
    "Joint",
    "MimicCommand",
    "ModelError",
    "RobotPart",
    "RobotSpec",
    "RosPluginConfig",
    "Sensor",
    "StateColumn",
    "Transmission",
    "TransmissionKind",
    "floating_base",
    "initial_command",
    "load",
    "load_string",
    "load_with_mjspec",
    "model_names",
    "model_path",
    "read_description",
]
