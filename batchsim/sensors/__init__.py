"""Cameras, lidars and sensor noise for every world, backend-free.

    camera.py   Camera, CameraInfo: an MJCF camera and its intrinsics (sensor_msgs/CameraInfo as data)
    lidar.py    Lidar: rangefinder groups and ray fans/grids, REP 117 ranges, point clouds
    noise.py    Noise, NoiseStream: Gaussian noise, per-world bias, dropout, seeded per world
    config.py   SensorConfig: mujoco_ros2_control's plugin YAML and batchsim's `sensors:` block
    suite.py    SensorSuite: all of it resolved against a model, and which worlds want what

Lidars declared in the MJCF (`<lidar>`, mujoco.plugin.lidar, rangefinder groups) are read by
batchsim/model/lidars.py, with the rest of the model. The system's side is its sensing part
(batchsim/parts/sensing.py: `render`, `scan`, `sensors`); the loop participant that produces what
is wanted is batchsim/loop/sampler.py; rendering and ray casting on the host (cpu, mjx) is
batchsim/backends/host_sensors.py.
"""

from __future__ import annotations

from batchsim.model.lidars import DeclarationError, SensorDeclarations
from batchsim.sensors.camera import Camera, CameraInfo, CameraMode
from batchsim.sensors.config import SensorConfig, SensorConfigError
from batchsim.sensors.lidar import Lidar, LidarKind
from batchsim.sensors.noise import Noise
from batchsim.sensors.suite import SensorSuite

__all__ = [
    "Camera",
    "CameraInfo",
    "CameraMode",
    "DeclarationError",
    "Lidar",
    "LidarKind",
    "Noise",
    "SensorConfig",
    "SensorConfigError",
    "SensorDeclarations",
    "SensorSuite",
]
