"""The plugins' parameters as mujoco_ros2_control's YAML gives them (a node's
`ros__parameters.mujoco_plugins`, beside the camera and lidar plugins batchsim.sensors.config
reads): which plugin types batchsim runs, and each one's params parsed.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from batchsim.plugins.base_velocity import PLUGIN_TYPE as BASE_VELOCITY_PLUGIN
from batchsim.plugins.base_velocity import BaseVelocityConfig
from batchsim.plugins.external_wrench import PLUGIN_TYPE as EXTERNAL_WRENCH_PLUGIN
from batchsim.plugins.external_wrench import ExternalWrenchConfig

#: the plugin types batchsim runs, one instance each: type -> (SensorConfig's field, its params' class)
RUN: dict[str, tuple[str, type]] = {
    BASE_VELOCITY_PLUGIN: ("base_velocity", BaseVelocityConfig),
    EXTERNAL_WRENCH_PLUGIN: ("external_wrench", ExternalWrenchConfig),
}

HEARTBEAT_PLUGIN = "mujoco_ros2_control_plugins/HeartbeatPublisherPlugin"
FREE_JOINT_STATE_PLUGIN = "mujoco_ros2_control_plugins/FreeJointStatePublisherPlugin"
#: plugins batchsim does not run, and what a user has instead
NOT_RUN = {
    HEARTBEAT_PLUGIN: "no mujoco_heartbeat topic: /clock and /diagnostics show the simulation is alive",
    FREE_JOINT_STATE_PLUGIN: "no free_joint_states topic: free bodies' poses are on /tf (and odom for the robot's base)",
}


def parse_plugin(kind: str, name: str, params: Mapping[str, Any], at: str) -> tuple[str, Any]:
    """A plugin batchsim runs (`kind` in RUN): the field it fills and its params parsed (`at`:
    the file and key path). ValueError: one line naming `at` and the key at fault."""
    field, config = RUN[kind]
    return field, config.parse(name, params, at)
