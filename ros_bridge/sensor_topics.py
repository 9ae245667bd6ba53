"""Cameras and lidars over the bridge: what each world publishes, the shared memory that
carries images and scans to the workers, and the physics side that fills it. No rclpy here.

Per world, under its namespace `<ns>` (topic names from the camera's or lidar's
configuration: mujoco_ros2_control's plugin YAML, batchsim's `sensors:` block, else these):

    <ns>/<camera>/image_raw          sensor_msgs/Image rgb8          } one render per frame,
    <ns>/<camera>/depth/image_raw    sensor_msgs/Image 32FC1, metres } at the camera rate,
    <ns>/<camera>/camera_info        sensor_msgs/CameraInfo          } one stamp
    <ns>/scan                        sensor_msgs/LaserScan (a 2D lidar, one row of rays)
    <ns>/points                      sensor_msgs/PointCloud2 (a 3D lidar), x y z float32, organized
                                     (height = rows, width = columns), NaN where no return

Frame ids are `<ns>/<frame>` (the frame from the configuration), as the bridge's other
frames, so every world's frames are distinct in one TF tree.

Shared memory, per camera k and lidar k (`SensorPlan.arrays`):

    cam{k}.rgb (nworld, H, W, 3) u1, cam{k}.depth (nworld, H, W) f4, lid{k}.ranges (nworld, nray) f4
    {cam,lid}{k}.seq (nworld,) i8    per world: odd while its row is written, even when done;
                                     a worker publishes a world's sample once, when its seq moved
    {cam,lid}{k}.time (nworld,) f8   per world: the sim time of its sample (the stamp)
    {cam,lid}{k}.parts (nworld,) u1  per world: which arrays its last sample wrote (PART_BITS)
    sensors.want (nworld, nsensor) u1  per world and sensor (cameras, then lidars): WANT_* bits of
                                     the topics with a subscriber; each worker writes its worlds'

The physics side (`SensorFeed`, a loop participant right after the bridge host) turns the
want bits into `sim.sensors.want/unwant` each period and runs a `SensorSampler`, which
renders and scans only wanted worlds at their rates; each sample's rows are copied into
the blocks (RGB only for worlds that want RGB, depth likewise). So a camera nobody
subscribes to is never rendered.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from batchsim.hardware import BatchedSystem
from batchsim.sampler import Sample, SensorSampler
from batchsim.sensors import Camera, CameraMode, Lidar

WANT_RGB = 1  # <camera>/image_raw, or a lidar's topic
WANT_DEPTH = 2  # <camera>/depth/image_raw
WANT_INFO = 4  # <camera>/camera_info (renders too: its stamps are the frames')
PART_BITS = {"rgb": WANT_RGB, "depth": WANT_DEPTH, "ranges": WANT_RGB}  # which rows a sample wrote


@dataclasses.dataclass(frozen=True)
class CameraTopics:
    """One camera's topics: `camera` (its size, intrinsics, frame id and topic names, relative
    to each world's namespace) at `rate` Hz."""

    camera: Camera
    rate: float


@dataclasses.dataclass(frozen=True)
class LidarTopics:
    """One lidar's topic: `lidar` (its rays, angles, range limits, frame id and topic) at
    `rate` Hz; LaserScan when it has one row of rays, else PointCloud2."""

    lidar: Lidar
    rate: float


@dataclasses.dataclass(frozen=True)
class SensorPlan:
    """Every camera and lidar the bridge publishes, in `sensors.want` column order
    (cameras, then lidars). Picklable: part of the FleetPlan. `batched`: the backend produces
    every wanted world in one period (warp), else spread over the sensor's period (cpu, mjx)."""

    cameras: tuple[CameraTopics, ...]
    lidars: tuple[LidarTopics, ...]
    batched: bool = True

    @property
    def nsensor(self) -> int:
        return len(self.cameras) + len(self.lidars)

    def arrays(self, nworld: int) -> list[tuple[str, tuple[int, ...], str]]:
        """The Layout entries of the sensor blocks for `nworld` worlds."""
        out: list[tuple[str, tuple[int, ...], str]] = [("sensors.want", (nworld, max(1, self.nsensor)), "u1")]
        for k, topics in enumerate(self.cameras):
            cam = topics.camera
            out += [
                (f"cam{k}.rgb", (nworld, cam.height, cam.width, 3), "u1"),
                (f"cam{k}.depth", (nworld, cam.height, cam.width), "f4"),
                (f"cam{k}.seq", (nworld,), "i8"),
                (f"cam{k}.time", (nworld,), "f8"),
                (f"cam{k}.parts", (nworld,), "u1"),
            ]
        for k, topics in enumerate(self.lidars):
            ld = topics.lidar
            out += [
                (f"lid{k}.ranges", (nworld, ld.nray), "f4"),
                (f"lid{k}.seq", (nworld,), "i8"),
                (f"lid{k}.time", (nworld,), "f8"),
                (f"lid{k}.parts", (nworld,), "u1"),
            ]
        return out


def sensor_plan(sim: BatchedSystem) -> SensorPlan | None:
    """The streaming cameras and the lidars of `sim` as topics; None when it has neither.
    (A polled camera renders when triggered, which no topic does: it gets none.)"""
    suite = sim.sensors
    cameras = tuple(CameraTopics(c, suite.camera_rate) for c in suite.cameras.values() if c.mode is CameraMode.STREAMING)
    lidars = tuple(LidarTopics(ld, ld.rate or suite.lidar_rate) for ld in suite.lidars.values())
    if not cameras and not lidars:
        return None
    return SensorPlan(cameras, lidars, batched=sim.sensors_batched)


class SensorBlock:
    """One camera's or lidar's arrays in shared memory, and its per-world seqlock.

    Args:
      memory: the shared arrays (batchsim.memory.Memory, or anything indexable by name).
      prefix: "cam{k}" or "lid{k}".
      parts: the data arrays' names after the prefix ("rgb", "depth" or "ranges").
    """

    def __init__(self, memory, prefix: str, parts: tuple[str, ...]):
        self.data = {p: memory[f"{prefix}.{p}"] for p in parts}
        self.seq = memory[f"{prefix}.seq"]
        self.time = memory[f"{prefix}.time"]
        self.parts = memory[f"{prefix}.parts"]

    def write(self, worlds: np.ndarray, time: float, rows: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
        """Write a sample of `worlds` (n,): per part, (the worlds it is written for, their
        rows); seq goes odd, then even, so a reader never takes a torn row for whole."""
        self.seq[worlds] += 1
        self.parts[worlds] = 0
        for part, (where, values) in rows.items():
            if len(where):
                self.data[part][where] = values
                self.parts[where] |= PART_BITS[part]
        self.time[worlds] = time
        self.seq[worlds] += 1

    def read(self, lo: int, hi: int, seen: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """The rows of worlds [lo, hi) written since `seen` ((hi - lo,) seq values, updated):
        (local rows (n,), which parts each holds (n,) PART_BITS, stamps (n,) f8 sim seconds,
        per part (n, ...) copies)."""
        before = self.seq[lo:hi].copy()
        rows = np.flatnonzero((before != seen) & (before % 2 == 0))
        if not rows.size:
            return rows, np.zeros(0, np.uint8), np.zeros(0), {}
        worlds = rows + lo
        time = self.time[worlds]
        parts = self.parts[worlds]
        data = {p: a[worlds] for p, a in self.data.items()}  # fancy indexing: copies
        whole = self.seq[worlds] == before[rows]  # not rewritten while we copied
        if not whole.all():  # those come again, newer, next time
            rows, time, parts = rows[whole], time[whole], parts[whole]
            data = {p: a[whole] for p, a in data.items()}
        seen[rows] = before[rows]
        return rows, parts, time, data


class SensorFeed:
    """The physics side of the sensor topics: a loop participant after the bridge host.

    Each period: the workers' want bits become `sim.sensors.want/unwant`; the sampler
    renders and scans what is wanted and due; each sample goes into shared memory, where
    the workers (woken by the host's snapshot of the same period) publish it.

    Args:
      sim: the system.
      memory: the bridge's shared arrays (BridgeHost.memory).
      plan: the sensors' plan (FleetPlan.sensors).

    Attributes:
      sampler: the SensorSampler; `sampler.produced` counts world-frames and world-scans.
    """

    def __init__(self, sim: BatchedSystem, memory, plan: SensorPlan):
        self.plan = plan
        self.want = memory["sensors.want"]
        self.names = [c.camera.name for c in plan.cameras] + [ld.lidar.name for ld in plan.lidars]
        self.blocks = {c.camera.name: SensorBlock(memory, f"cam{k}", ("rgb", "depth")) for k, c in enumerate(plan.cameras)}
        self.blocks.update({ld.lidar.name: SensorBlock(memory, f"lid{k}", ("ranges",)) for k, ld in enumerate(plan.lidars)})
        self.column = {name: s for s, name in enumerate(self.names)}
        self._wanted = np.zeros_like(self.want)
        self.sampler = SensorSampler(sim, [self._write])
        # cameras and lidars the bridge does not publish (a polled camera) stay unwanted
        self.sampler.produced = {name: n for name, n in self.sampler.produced.items() if name in self.column}

    def update(self, sim: BatchedSystem, time: float, period: float) -> None:
        want = self.want.copy()
        changed = np.flatnonzero((want != self._wanted).any(axis=0))
        for s in changed.tolist():
            mask = want[:, s] != 0
            sim.sensors.want(self.names[s], np.flatnonzero(mask))
            sim.sensors.unwant(self.names[s], np.flatnonzero(~mask))
        self._wanted = want
        self.sampler.update(sim, time, period)

    def _write(self, sample: Sample) -> None:
        block = self.blocks.get(sample.name)
        if block is None:
            return
        worlds = sample.worlds
        if sample.ranges is not None:
            block.write(worlds, sample.time, {"ranges": (worlds, sample.ranges)})
            return
        bits = self._wanted[worlds, self.column[sample.name]]
        block.write(
            worlds,
            sample.time,
            {"rgb": _rows(worlds, sample.rgb, (bits & WANT_RGB) != 0), "depth": _rows(worlds, sample.depth, (bits & WANT_DEPTH) != 0)},
        )


def _rows(worlds: np.ndarray, values: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(worlds, values) where `keep`, without a copy when every world is kept."""
    return (worlds, values) if keep.all() else (worlds[keep], values[keep])
