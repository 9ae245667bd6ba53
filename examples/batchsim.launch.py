"""`ros2 launch examples/batchsim.launch.py worlds:=16 model:=arm` where ROS 2 is installed.

Starts `batchsim` as one process of a launch description, beside the user's own nodes, with
its usual arguments as launch arguments. `extra_args:="--rtf 2 --sensors s.yaml"` passes any
other flag; ROS arguments (`--ros-args -p use_sim_time:=true`) go to every bridge worker, as
the command line takes them. The `batchsim` executable is the one on PATH (the checkout's
`.venv/bin` after `make install`), or `batchsim_exe:=/path/to/batchsim`.

Include it from a launch file of your own:

    IncludeLaunchDescription(PythonLaunchDescriptionSource("/path/to/batchsim.launch.py"),
                             launch_arguments={"worlds": "4", "ros2_control": "robot.urdf"}.items())
"""

from __future__ import annotations

import shlex

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess, OpaqueFunction
from launch.substitutions import LaunchConfiguration

# launch argument -> (batchsim flag, default, description); "" default: the flag is not passed
ARGUMENTS = {
    "worlds": ("--worlds", "16", "number of worlds"),
    "model": ("--model", "", "shipped model name or MJCF/URDF path (default: batchsim's)"),
    "backend": ("--backend", "", "cpu, mjx, warp or auto (default: auto)"),
    "ros2_control": ("--ros2-control", "", "URDF/XML with a <ros2_control> block (xacro args after the path)"),
    "controllers": ("--controllers", "", "controller_manager YAML ('none': no controllers)"),
    "sensors": ("--sensors", "", "mujoco_ros2_control plugin YAML and/or batchsim's sensors: block"),
    "namespace": ("--namespace", "", "world namespace template (default world_{i}; '' with one world: the root)"),
    "robot_description_topic": ("--robot-description-topic", "", "take the URDF from this topic"),
}


def command(values: dict[str, str], exe: str = "batchsim", extra: str = "") -> list[str]:
    """The batchsim command line the launch arguments make: a value of "" passes no flag;
    `root_namespace` "true" passes `--namespace ''` (one world at the root)."""
    argv = [exe]
    for name, (flag, _default, _help) in ARGUMENTS.items():
        if values.get(name, ""):
            argv += [flag, values[name]]
    if values.get("root_namespace", "false").lower() == "true":
        argv += ["--namespace", ""]
    return argv + shlex.split(extra)


def _process(context, *args, **kwargs):
    values = {name: LaunchConfiguration(name).perform(context) for name in (*ARGUMENTS, "root_namespace")}
    argv = command(
        values,
        LaunchConfiguration("batchsim_exe").perform(context),
        LaunchConfiguration("extra_args").perform(context),
    )
    return [ExecuteProcess(cmd=argv, output="screen", emulate_tty=True, name="batchsim")]


def generate_launch_description() -> LaunchDescription:
    declared = [DeclareLaunchArgument(name, default_value=d, description=h) for name, (_f, d, h) in ARGUMENTS.items()]
    declared += [
        DeclareLaunchArgument("root_namespace", default_value="false", description="true: one world at the root namespace"),
        DeclareLaunchArgument("extra_args", default_value="", description="any other batchsim flags, as one string"),
        DeclareLaunchArgument("batchsim_exe", default_value="batchsim", description="the batchsim executable"),
    ]
    return LaunchDescription([*declared, OpaqueFunction(function=_process)])
