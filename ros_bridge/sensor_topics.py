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
    (the blocks' and the want bits' writers and readers: ros_bridge/protocol/sensor_blocks.py)

The physics side (`SensorFeed`, a loop participant right after the bridge host) turns the
want bits into `sim.sensors.want/unwant` each period and runs a `SensorSampler`, which
renders and scans only wanted worlds at their rates; each sample's rows are copied into
the blocks (RGB only for worlds that want RGB, depth likewise). So a camera nobody
subscribes to is never rendered. A recording of camera or lidar topics (ros_bridge/recording.py)
adds its want bits for the recorded worlds while it runs, and with `--rtf 0` a sample waits
for the recorder to have taken the one before it; the web view adds RGB for the camera of the
world each of its browsers shows (ros_bridge/view_plan.py's ViewCamera).
"""

from __future__ import annotations

import dataclasses
import enum

import numpy as np

from batchsim.contract import Contract
from batchsim.loop import Participant
from batchsim.loop.sampler import Sample, SensorSampler
from batchsim.sensors import Camera, CameraMode, Lidar
from ros_bridge.protocol.sensor_blocks import (
    WANT_DEPTH,
    WANT_INFO,
    WANT_RGB,
    SensorBlock,
    want_arrays,
    wanted,
)


class TopicKind(enum.Enum):
    """What a camera's or lidar's topic carries."""

    IMAGE = "image"  # the block's rgb part, rgb8
    DEPTH = "depth"  # the depth part, 32FC1 metres
    INFO = "camera_info"  # no part: the camera's constants, stamped like its frames
    SCAN = "scan"  # a 2D lidar's ranges, LaserScan
    CLOUD = "points"  # a 3D lidar's ranges as points, PointCloud2

    @property
    def msg_type(self) -> str:
        return _MSG_TYPES[self]


_MSG_TYPES = {
    TopicKind.IMAGE: "sensor_msgs/msg/Image",
    TopicKind.DEPTH: "sensor_msgs/msg/Image",
    TopicKind.INFO: "sensor_msgs/msg/CameraInfo",
    TopicKind.SCAN: "sensor_msgs/msg/LaserScan",
    TopicKind.CLOUD: "sensor_msgs/msg/PointCloud2",
}


@dataclasses.dataclass(frozen=True)
class SensorTopic:
    """One topic of one camera or lidar: `sensor` its column in `sensors.want` (cameras, then
    lidars), `name` relative to a world's namespace, `kind`, `want` the WANT_* bit that asks
    for it, `part` the sensor block's array its payload comes from (None: CameraInfo)."""

    sensor: int
    name: str
    kind: TopicKind
    want: int
    part: str | None


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

    def topics(self) -> list[SensorTopic]:
        """Every camera's and lidar's topic, in `sensors.want` column order."""
        out = []
        for s, ct in enumerate(self.cameras):
            cam = ct.camera
            out += [
                SensorTopic(s, cam.image_topic.strip("/"), TopicKind.IMAGE, WANT_RGB, "rgb"),
                SensorTopic(s, cam.depth_topic.strip("/"), TopicKind.DEPTH, WANT_DEPTH, "depth"),
                SensorTopic(s, cam.info_topic.strip("/"), TopicKind.INFO, WANT_INFO, None),
            ]
        for s, lt in enumerate(self.lidars, start=len(self.cameras)):
            kind = TopicKind.CLOUD if lt.lidar.is_3d else TopicKind.SCAN
            out.append(SensorTopic(s, lt.lidar.topic.strip("/"), kind, WANT_RGB, "ranges"))
        return out

    def source(self, s: int) -> tuple[Camera | Lidar, float | None]:
        """Sensor `s` (`sensors.want` column order): its Camera, or its Lidar and rate."""
        ncam = len(self.cameras)
        return (self.cameras[s].camera, None) if s < ncam else (self.lidars[s - ncam].lidar, self.lidars[s - ncam].rate)

    def block(self, memory, s: int) -> SensorBlock:
        """Sensor `s`'s block in `memory` (`sensors.want` column order): a camera's rgb and
        depth, a lidar's ranges, as `arrays` lays them out."""
        ncam = len(self.cameras)
        return SensorBlock(memory, f"cam{s}", ("rgb", "depth")) if s < ncam else SensorBlock(memory, f"lid{s - ncam}", ("ranges",))

    def arrays(self, nworld: int) -> list[tuple[str, tuple[int, ...], str]]:
        """The Layout entries of the sensor blocks for `nworld` worlds."""
        out = want_arrays(nworld, self.nsensor)
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


def sensor_plan(sim: Contract) -> SensorPlan | None:
    """The streaming cameras and the lidars of `sim` as topics; None when it has neither.
    (A polled camera renders when triggered, which no topic does: it gets none.)"""
    suite = sim.sensors
    cameras = tuple(CameraTopics(c, suite.camera_rate) for c in suite.cameras.values() if c.mode is CameraMode.STREAMING)
    lidars = tuple(LidarTopics(ld, ld.rate or suite.lidar_rate) for ld in suite.lidars.values())
    if not cameras and not lidars:
        return None
    return SensorPlan(cameras, lidars, batched=sim.sensors_batched)


class SensorFeed(Participant):
    """The physics side of the sensor topics: a loop participant after the bridge host.

    Each period: the workers' want bits become `sim.sensors.want/unwant`; the sampler
    renders and scans what is wanted and due; each sample goes into shared memory, where
    the workers (woken by the host's snapshot of the same period) publish it.

    Args:
      sim: the system.
      memory: the bridge's shared arrays (BridgeHost.memory).
      plan: the sensors' plan (FleetPlan.sensors).
      recording: the recording participant (ros_bridge/recording.py's Recording), or None.
      view: the web view's camera request (ros_bridge/view_plan.py's ViewCamera), or None.

    Attributes:
      sampler: the SensorSampler; `sampler.produced` counts world-frames and world-scans.
    """

    def __init__(self, sim: Contract, memory, plan: SensorPlan, recording=None, view=None):
        self.plan = plan
        self.recording = recording
        self.askers = [a for a in (recording, view) if a is not None]  # each ORs its want bits in
        self.memory = memory
        self.names = [c.camera.name for c in plan.cameras] + [ld.lidar.name for ld in plan.lidars]
        self.blocks = {name: plan.block(memory, s) for s, name in enumerate(self.names)}
        self.column = {name: s for s, name in enumerate(self.names)}
        self._wanted = np.zeros_like(wanted(memory))
        self.sampler = SensorSampler(sim, [self._write])
        # cameras and lidars the bridge does not publish (a polled camera) stay unwanted
        self.sampler.produced = {name: n for name, n in self.sampler.produced.items() if name in self.column}

    def update(self, sim: Contract, time: float, period: float) -> None:
        want = wanted(self.memory)
        for asker in self.askers:
            asker.want_sensors(want)
        changed = np.flatnonzero((want != self._wanted).any(axis=0))
        for s in changed.tolist():
            mask = want[:, s] != 0
            sim.sensors.want(self.names[s], np.flatnonzero(mask))
            sim.sensors.unwant(self.names[s], np.flatnonzero(~mask))
        self._wanted = want
        self.sampler.update(sim, time, period)

    def on_stop(self, sim: Contract, time: float) -> None:
        """The run is over: the renders still in flight go into the blocks, where a recording,
        which finishes after the loop, takes them (a --duration run's last frames)."""
        self.sampler.on_stop(sim, time)

    def _write(self, sample: Sample) -> None:
        block = self.blocks.get(sample.name)
        if block is None:
            return
        worlds = sample.worlds
        if self.recording is not None:
            self.recording.hold_sensor(self.column[sample.name], block.seq, worlds)
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
