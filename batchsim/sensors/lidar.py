"""Lidars: fans (2D) and grids (3D) of rays from a site, as LaserScan and PointCloud2 data.

Two kinds:

- RANGEFINDER: MJCF rangefinder sensors replicated around a site, mujoco_ros2_control's
  arrangement (its converter turns `<lidar ref_site= sensor_name= min_angle= max_angle=
  angle_increment=/>` into `<replicate>`d sites with one rangefinder each, named
  `<name>-00`, `<name>-01`, ...). MuJoCo computes them at every physics step; a scan reads
  them from sensordata.
- RAYCAST: rays cast in bulk by the backend when a scan is asked for, with no MJCF sensor
  at all (MuJoCo Warp's ray casting on warp, mujoco.batch's threaded ray casting on cpu).
  A `<lidar>` element in the MJCF or ros2_control file, mujoco_ros2_control's
  `mujoco.plugin.lidar` sensors, and batchsim's own `lidars:` YAML become these.

Directions are unit vectors in the site's frame, REP 103: azimuth about z from x towards
y, elevation from the xy plane towards z; ray (row e, column a) is index e * ncol + a.
Ranges follow REP 117: +inf where a ray hit nothing within range_max, -inf where it hit
closer than range_min, NaN where noise dropped it.
"""

from __future__ import annotations

import dataclasses
import enum
import math

import mujoco
import numpy as np

from batchsim.model.lidars import RangefinderGroup
from batchsim.sensors.config import SensorConfigError

DEFAULT_RANGE_MAX = 1000.0  # mujoco_ros2_control's default


class LidarKind(enum.Enum):
    RANGEFINDER = "rangefinder"  # read from MJCF rangefinder sensors in sensordata
    RAYCAST = "raycast"  # cast in bulk by the backend


@dataclasses.dataclass(frozen=True)
class Lidar:
    """One lidar every world scans with.

    Attributes:
      name: the lidar's name (a rangefinder group's prefix, a plugin sensor's or YAML name).
      kind: RANGEFINDER or RAYCAST.
      site, site_id: the site the rays start from and whose frame `directions` are in.
      body_id: the body whose geoms the rays ignore (the site's, as MuJoCo's rangefinder).
      directions: (nray, 3) float64 unit ray directions in the site frame.
      ncol, nrow: rays per row (azimuth) and rows (elevation); nray = nrow * ncol.
      angle_min, angle_max, angle_increment: azimuth of the first and last column and the
        step, radians (LaserScan's fields).
      elevation_min, elevation_max: elevation of the first and last row.
      range_min, range_max: metres; beyond them a range is -inf / +inf.
      frame_id: the frame scans are stamped in; topic: relative to each world's namespace.
      rate: Hz at which scans are wanted (None: the lidar rate of the run).
      sensor_adr: (nray,) sensordata addresses of the rangefinders (RANGEFINDER only).
    """

    name: str
    kind: LidarKind
    site: str
    site_id: int
    body_id: int
    directions: np.ndarray
    ncol: int
    nrow: int
    angle_min: float
    angle_max: float
    angle_increment: float
    elevation_min: float
    elevation_max: float
    range_min: float
    range_max: float
    frame_id: str
    topic: str
    rate: float | None = None
    sensor_adr: np.ndarray | None = None

    @property
    def nray(self) -> int:
        return self.nrow * self.ncol

    @property
    def is_3d(self) -> bool:
        """Several rows: published as PointCloud2 rather than LaserScan."""
        return self.nrow > 1

    def ranges(self, distance: np.ndarray) -> np.ndarray:
        """REP 117 ranges (n, nray) float32 from ray distances (n, nray), where < 0 is a miss."""
        dist = np.asarray(distance)
        out = dist.astype(np.float32)
        out[(dist < 0) | (dist > self.range_max)] = np.inf
        out[(dist >= 0) & (dist < self.range_min)] = -np.inf
        return out

    def points(self, ranges: np.ndarray) -> np.ndarray:
        """(n, nray, 3) float32 points in the site frame; NaN where a range is not finite."""
        r = np.asarray(ranges, np.float32)
        pts = r[..., None] * self.directions.astype(np.float32)
        pts[~np.isfinite(r)] = np.nan
        return pts


def fan(azimuth: np.ndarray, elevation: np.ndarray) -> np.ndarray:
    """(nrow * ncol, 3) unit directions, one row per elevation, one column per azimuth."""
    a, e = np.meshgrid(np.asarray(azimuth, np.float64), np.asarray(elevation, np.float64))
    return np.stack([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)], -1).reshape(-1, 3)


def element_angles(min_angle: float, max_angle: float, angle_increment: float) -> np.ndarray:
    """The azimuths mujoco_ros2_control's converter replicates a `<lidar>` element's rangefinders at."""
    count = int((max_angle - min_angle) / angle_increment) + 1
    return min_angle + angle_increment * np.arange(count)


def linspace(lower: float, upper: float, n: int) -> np.ndarray:
    """n angles from lower to upper inclusive (n == 1: lower), as mujoco.plugin.lidar spaces them."""
    return np.linspace(lower, upper, n) if n > 1 else np.array([lower], np.float64)


def group_geometry(
    m: mujoco.MjModel, group: RangefinderGroup
) -> tuple[int, np.ndarray, float, float, float]:
    """(frame site, directions (nray, 3) in its frame, angle_min, angle_max, angle_increment) of a group.

    The frame is the site mujoco_ros2_control's converter hung the rangefinders from (its
    `<site>_lidar_body` body sits beside a site `<site>`), in which the fan is planar with
    azimuths about z; without one, the first rangefinder's site, with angles measured from
    the first ray about the fan's axis.
    """
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    # a rangefinder looks along its site's z axis
    world_dirs = np.stack([d.site_xmat[s].reshape(3, 3)[:, 2] for s in group.sites])
    body = m.body(int(m.site_bodyid[group.sites[0]])).name
    frame = -1
    if body.endswith("_lidar_body"):
        frame = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, body.removesuffix("_lidar_body"))
    if frame >= 0:
        dirs = world_dirs @ d.site_xmat[frame].reshape(3, 3)
        angles = np.arctan2(dirs[:, 1], dirs[:, 0])
    else:
        frame = group.sites[0]
        dirs = world_dirs @ d.site_xmat[frame].reshape(3, 3)
        axis = np.cross(dirs[0], dirs[-1]) if len(dirs) > 1 else np.zeros(3)
        if np.linalg.norm(axis) < 1e-9:
            axis = np.array([0.0, 0.0, 1.0])
        axis /= np.linalg.norm(axis)
        angles = np.arctan2(np.cross(dirs[0], dirs) @ axis, dirs @ dirs[0])
    angles = np.unwrap(angles)
    increment = float((angles[-1] - angles[0]) / (len(angles) - 1)) if len(angles) > 1 else 0.0
    return frame, dirs, float(angles[0]), float(angles[-1]), increment


def check_range(name: str, range_min: float, range_max: float, where: str) -> None:
    if not (math.isfinite(range_min) and math.isfinite(range_max)) or not 0 <= range_min < range_max:
        raise SensorConfigError(f"{where}: lidar {name!r}: need 0 <= range_min < range_max, got {range_min:g}, {range_max:g}")
