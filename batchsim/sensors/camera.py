"""Cameras: an MJCF `<camera>` as an RGB-D sensor, with its intrinsics as CameraInfo data.

The intrinsics are those MuJoCo renders with. A camera given by `fovy` (degrees, vertical)
has square pixels and a centred principal point; one given by `sensorsize` and `focal` /
`focalpixel` / `principal` has those, the sensor cropped to the image's aspect ratio as
MuJoCo does. Pixel coordinates follow ROS (OpenCV): pixel (u, v) has its centre at
integer u, v, so a centred principal point is ((W - 1) / 2, (H - 1) / 2).
"""

from __future__ import annotations

import dataclasses
import enum
import math

import mujoco
import numpy as np

DEFAULT_RESOLUTION = (320, 240)  # (width, height) for a camera whose MJCF gives none


class CameraMode(enum.Enum):
    """mujoco_ros2_control's `camera_type`: how a camera is driven."""

    STREAMING = "streaming"  # rendered at the camera rate
    POLLED = "polled"  # rendered when triggered
    DISABLED = "disabled"  # never rendered


@dataclasses.dataclass(frozen=True)
class CameraInfo:
    """sensor_msgs/CameraInfo's calibration fields, as data (row-major matrices)."""

    width: int
    height: int
    k: tuple[float, ...]  # 3x3 intrinsic matrix
    p: tuple[float, ...]  # 3x4 projection matrix
    d: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)  # no distortion
    r: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    distortion_model: str = "plumb_bob"

    @property
    def fx(self) -> float:
        return self.k[0]

    @property
    def fy(self) -> float:
        return self.k[4]

    @property
    def cx(self) -> float:
        return self.k[2]

    @property
    def cy(self) -> float:
        return self.k[5]


@dataclasses.dataclass(frozen=True)
class Camera:
    """One camera every world renders.

    Attributes:
      name: the MJCF camera's name.
      id: its MuJoCo camera id.
      width, height: image size in pixels; images are (nworld, height, width, 3) uint8 RGB
        and (nworld, height, width) float32 depth in metres along the optical axis.
      info: the calibration, for sensor_msgs/CameraInfo.
      frame_id: the frame the images are stamped in (ROS optical frame: z forward, y down).
      image_topic, depth_topic, info_topic: topic names relative to each world's namespace.
      mode: streaming, polled or disabled (mujoco_ros2_control's camera_type).
    """

    name: str
    id: int
    width: int
    height: int
    info: CameraInfo
    frame_id: str
    image_topic: str
    depth_topic: str
    info_topic: str
    mode: CameraMode = CameraMode.STREAMING

    @property
    def pixels(self) -> int:
        return self.width * self.height


def intrinsics(m: mujoco.MjModel, cam: int, width: int, height: int) -> CameraInfo:
    """The calibration MuJoCo renders camera `cam` with at `width` x `height` pixels."""
    W, H = float(width), float(height)
    sensor_w, sensor_h = (float(x) for x in m.cam_sensorsize[cam])
    if sensor_h > 0:
        # physical intrinsics, in length units: focal (fx, fy) and principal offset (cx, cy);
        # the sensor is cropped to the image's aspect ratio, as MuJoCo does
        f_x, f_y, c_x, c_y = (float(x) for x in m.cam_intrinsic[cam])
        if W / H > sensor_w / sensor_h:
            sensor_h = sensor_w * H / W
        elif W / H < sensor_w / sensor_h:
            sensor_w = sensor_h * W / H
        fx = W * f_x / sensor_w
        fy = H * f_y / sensor_h
        cx = W * (0.5 * sensor_w - c_x) / sensor_w - 0.5
        cy = H * (0.5 * sensor_h - c_y) / sensor_h - 0.5
    else:
        fx = fy = 0.5 * H / math.tan(math.radians(float(m.cam_fovy[cam])) / 2.0)
        cx, cy = (W - 1.0) / 2.0, (H - 1.0) / 2.0
    k = (fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0)
    p = (fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0)
    return CameraInfo(width=int(width), height=int(height), k=k, p=p)


def resolution_of(m: mujoco.MjModel, cam: int) -> tuple[int, int] | None:
    """The MJCF camera's `resolution` (width, height), or None where it gives none (MuJoCo's 1x1)."""
    w, h = (int(x) for x in m.cam_resolution[cam])
    return None if (w, h) == (1, 1) else (w, h)


def project(info: CameraInfo, points: np.ndarray) -> np.ndarray:
    """Pixel coordinates (u, v) of points (..., 3) given in the ROS optical frame (z forward)."""
    pts = np.asarray(points, np.float64)
    return np.stack([info.fx * pts[..., 0] / pts[..., 2] + info.cx, info.fy * pts[..., 1] / pts[..., 2] + info.cy], -1)
