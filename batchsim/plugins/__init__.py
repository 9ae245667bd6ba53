"""mujoco_ros2_control's plugins that act on the simulation, run in every world: the base
velocity plugin (base_velocity.py) and the external wrench plugin (external_wrench.py), each a
part of the system, and their parameters read from the plugin YAML (config.py).
"""

from __future__ import annotations

from batchsim.plugins.base_velocity import BaseDrive, BaseVelocity, BaseVelocityConfig
from batchsim.plugins.external_wrench import ExternalWrench, ExternalWrenchConfig, ExternalWrenches, Wrenches

__all__ = [
    "BaseDrive",
    "BaseVelocity",
    "BaseVelocityConfig",
    "ExternalWrench",
    "ExternalWrenchConfig",
    "ExternalWrenches",
    "Wrenches",
]
