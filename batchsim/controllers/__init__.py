"""ros2_control-style controllers, vectorized over worlds with NumPy; no ROS imports here.

    manager = load_controllers("controllers.yaml", sim.spec, sim.nworld)
    loop = SimLoop(sim, control_rate=manager.update_rate, participants=[manager])
    manager["arm_controller"].set_trajectory(5, joints, times, positions)

The YAML is ros2_control's controller_manager file. A controller declares its ROS topics
and actions as data (topics.py); the ROS bridge (ros_bridge/) binds them for every world.
"""

from __future__ import annotations

from batchsim.controllers.base import Controller, Params
from batchsim.controllers.broadcasters import (
    ForceTorqueSensorBroadcaster,
    IMUSensorBroadcaster,
    JointStateBroadcaster,
)
from batchsim.controllers.config import (
    CONTROLLER_TYPES,
    ManagerConfig,
    build,
    default_controllers,
    load_controllers,
    parse,
)
from batchsim.controllers.diff_drive import DiffDriveController
from batchsim.controllers.forward_command import (
    ForwardCommandController,
    JointGroupEffortController,
    JointGroupPositionController,
    JointGroupVelocityController,
)
from batchsim.controllers.gripper import (
    EffortGripperActionController,
    GripperActionController,
    ParallelGripperActionController,
)
from batchsim.controllers.manager import (
    ControllerInfo,
    ControllerManager,
    HardwareInterfaces,
    InterfaceInfo,
    Strictness,
    SwitchResult,
)
from batchsim.controllers.pose_broadcaster import PoseBroadcaster
from batchsim.controllers.topics import (
    ControllerTopics,
    Input,
    MessageKind,
    Output,
    TrajectoryBatch,
    Transform,
)
from batchsim.controllers.trajectory import JointTrajectoryController

__all__ = [
    "CONTROLLER_TYPES",
    "Controller",
    "ControllerInfo",
    "ControllerManager",
    "ControllerTopics",
    "DiffDriveController",
    "EffortGripperActionController",
    "ForceTorqueSensorBroadcaster",
    "ForwardCommandController",
    "GripperActionController",
    "HardwareInterfaces",
    "IMUSensorBroadcaster",
    "Input",
    "InterfaceInfo",
    "JointGroupEffortController",
    "JointGroupPositionController",
    "JointGroupVelocityController",
    "JointStateBroadcaster",
    "JointTrajectoryController",
    "ManagerConfig",
    "MessageKind",
    "Output",
    "ParallelGripperActionController",
    "Params",
    "PoseBroadcaster",
    "Strictness",
    "SwitchResult",
    "TrajectoryBatch",
    "Transform",
    "build",
    "default_controllers",
    "load_controllers",
    "parse",
]
