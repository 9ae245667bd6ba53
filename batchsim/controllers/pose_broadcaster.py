"""pose_broadcaster/PoseBroadcaster: a pose sensor of every world as geometry_msgs/PoseStamped."""

from __future__ import annotations

from typing import Any, ClassVar

import mujoco
import numpy as np

from batchsim.controllers.base import Controller, Params
from batchsim.controllers.topics import ControllerTopics, MessageKind, Output
from batchsim.model import RobotSpec
from batchsim.types import as_slice

_FIELDS = ("position.x", "position.y", "position.z", "orientation.x", "orientation.y", "orientation.z", "orientation.w")


class PoseBroadcaster(Controller):
    """pose_broadcaster/PoseBroadcaster: `<ns>/<controller>/pose` (geometry_msgs/PoseStamped).

    Parameters (stock): `pose_name`, the prefix of the seven state interfaces
    `<pose_name>/position.x` ... `/orientation.w` (a ros2_control sensor with
    `mujoco_type` `pose`), or a site or body of the MJCF that `framepos` and `framequat`
    sensors sit on; `frame_id`, the frame the pose is in. `tf.*` is accepted, but batchsim
    publishes no TF: subscribe to the pose topic instead.

    Attributes:
      position: (nworld, 3); orientation: (nworld, 4) x, y, z, w (ROS order).
    """

    TYPE: ClassVar[str] = "pose_broadcaster/PoseBroadcaster"
    ACCEPTED = (*Controller.ACCEPTED, "tf")

    def __init__(self, name: str, params: Params, spec: RobotSpec, nworld: int):
        super().__init__(name, params, spec, nworld)
        self.pose_name = params.string("pose_name")
        self.frame_id = params.string("frame_id")
        names = [f"{self.pose_name}/{f}" for f in _FIELDS]
        if not all(n in self._state_names for n in names):
            names = self._frame_sensor_columns()
        self._cols = as_slice(self.state_columns("pose_name", names))
        self.pose = np.zeros((self.nworld, 7))
        self.pose[:, 6] = 1.0

    def _frame_sensor_columns(self) -> list[str]:
        """The columns of MJCF framepos/framequat sensors on the site or body `pose_name`."""
        on_pose = [s for s in self.spec.sensors if s.objname == self.pose_name]
        pos = next((s for s in on_pose if s.type == mujoco.mjtSensor.mjSENS_FRAMEPOS), None)
        quat = next((s for s in on_pose if s.type == mujoco.mjtSensor.mjSENS_FRAMEQUAT), None)
        if pos is None or quat is None:
            raise self.params.error(
                "pose_name",
                f"the model has no pose {self.pose_name!r}: no state interfaces {self.pose_name}/position.x ... "
                f"(a ros2_control sensor with mujoco_type pose) and no framepos + framequat sensors on a "
                f"site or body of that name",
            )
        return [f"{(pos if f.startswith('position') else quat).name}/{f}" for f in _FIELDS]

    @property
    def position(self) -> np.ndarray:
        return self.pose[:, :3]

    @property
    def orientation(self) -> np.ndarray:
        return self.pose[:, 3:]

    def update(self, sim: Any, time: float, period: float) -> None:
        self.pose[:] = sim.state[:, self._cols]

    def topics(self) -> ControllerTopics:
        """`<ns>/<controller>/pose`."""
        fields = {"position": self.position, "orientation": self.orientation}
        pose = Output(f"{self.name}/pose", MessageKind.POSE_STAMPED, lambda: fields, frame_id=self.frame_id)
        return ControllerTopics(self.name, outputs=(pose,))
