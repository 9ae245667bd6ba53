"""The controller types a controller_manager YAML may name, by their plugin name
(`joint_trajectory_controller/JointTrajectoryController`, ...): the one table the YAML's
parser (config.py) and the manager's list of types (manager.py) read."""

from __future__ import annotations

from batchsim.controllers.base import Controller
from batchsim.controllers.broadcasters import (
    ForceTorqueSensorBroadcaster,
    IMUSensorBroadcaster,
    JointStateBroadcaster,
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
from batchsim.controllers.policy import PolicyController
from batchsim.controllers.pose_broadcaster import PoseBroadcaster
from batchsim.controllers.trajectory import JointTrajectoryController

CONTROLLER_TYPES: dict[str, type[Controller]] = {
    c.TYPE: c
    for c in (
        JointStateBroadcaster,
        ForwardCommandController,
        JointGroupPositionController,
        JointGroupVelocityController,
        JointGroupEffortController,
        JointTrajectoryController,
        DiffDriveController,
        IMUSensorBroadcaster,
        ForceTorqueSensorBroadcaster,
        PoseBroadcaster,
        GripperActionController,
        ParallelGripperActionController,
        EffortGripperActionController,
        PolicyController,
    )
}
