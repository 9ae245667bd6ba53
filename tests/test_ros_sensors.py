"""Cameras and lidars over the ROS 2 bridge (ros_bridge/sensor_*.py). Domains 70-79 belong
to this file.

- One rover fleet (3 worlds, 2 bridge workers: worlds 0-1 and 2), configured by a
  mujoco_ros2_control plugin YAML (camera and lidar topic and frame names, absolute, as
  real configurations write them) and a dense 3D lidar from batchsim's block, serves the
  checks over real DDS: Image, depth Image, CameraInfo, LaserScan and PointCloud2 arrive
  under each world's namespace, stamped in sim time, and differ between worlds placed
  differently.
- In the test process, with the bridge inside it (`workers=0`): a camera nobody subscribes
  to is never rendered, and stops being rendered when its last subscriber goes.
- The bulk CDR framing deserializes to the messages rclpy would build.
"""

from __future__ import annotations

import math
import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import need

rclpy = need("rclpy")  # skips where ROS is absent, fails instead under BATCHSIM_FORCE_BACKENDS=1

from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.serialization import deserialize_message  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402
from ros_fleet import LOCALHOST, Fleet, bridge_workers, domain_id, release_domain  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, LaserScan, PointCloud2  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402

import batchsim  # noqa: E402
from batchsim.loop import SimLoop  # noqa: E402
from ros_bridge.transport import MIN_SEGMENT, PROFILES_FILE  # noqa: E402

pytestmark = pytest.mark.ros

NWORLD = 3
W, H = 32, 24
CAMERA_RATE = 20.0
PLUGINS = """
mujoco_ros2_control:
  ros__parameters:
    mujoco_plugins:
      mujoco_camera_plugin:
        type: "mujoco_ros2_control_plugins/CameraPlugin"
        camera_publish_rate: 20.0
        front_camera:
          frame_name: camera_color_optical_frame
          image_topic: /camera/color/image_raw
          depth_topic: /camera/aligned_depth_to_color/image_raw
          info_topic: /camera/color/camera_info
      mujoco_3d_lidar_plugin:
        type: "mujoco_ros2_control_plugins/Mujoco3dLidarPlugin"
        base_scan: {frame_name: laser_frame, topic: /scan}
"""
RING = """
sensors:
  lidars:
    ring: {site: lidar, horizontal: {samples: 24, min_angle: -3.1416, max_angle: 2.8798},
           vertical: {samples: 3, min_angle: -0.1, max_angle: 0.1}, range_min: 0.05, range_max: 20, rate: 20}
"""
TOPICS = {
    "image": (Image, "camera/color/image_raw"),
    "depth": (Image, "camera/aligned_depth_to_color/image_raw"),
    "info": (CameraInfo, "camera/color/camera_info"),
    "scan": (LaserScan, "scan"),
    "points": (PointCloud2, "points"),
}


def sim_time(stamp) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


@pytest.fixture(scope="module")
def rovers(tmp_path_factory):
    d = tmp_path_factory.mktemp("rovers")
    (d / "plugins.yaml").write_text(PLUGINS)
    (d / "ring.yaml").write_text(RING)
    args = [
        "--model", "rover", "--worlds", str(NWORLD), "--bridge-workers", "2", "--camera-resolution", f"{W}x{H}",
        "--lidar-rate", "20", "--sensors", str(d / "plugins.yaml"), "--sensors", str(d / "ring.yaml"),
    ]  # fmt: skip
    with Fleet(domain_id(70), args, d / "batchsim.log") as f:
        f.sinks = {
            (kind, w): f.latest(msg_type, f"/world_{w}/{topic}", keep=6)
            for kind, (msg_type, topic) in TOPICS.items()
            for w in range(NWORLD)
        }
        f.clock = f.latest(Clock, "/clock")
        f.wait(lambda: all(s.count >= 3 for s in f.sinks.values()), 60, "every sensor topic of every world")
        yield f
        assert f.close() == 0, f.log()


def test_images_info_scans_and_clouds_arrive_under_each_namespace(rovers):
    fy = 0.5 * H / math.tan(math.radians(60.0) / 2)  # the rover camera's fovy
    for w in range(NWORLD):
        image = rovers.sinks["image", w].msg
        assert (image.encoding, image.width, image.height, image.step) == ("rgb8", W, H, 3 * W)
        assert len(image.data) == 3 * W * H and image.header.frame_id == f"world_{w}/camera_color_optical_frame"
        rgb = np.frombuffer(bytes(image.data), np.uint8).reshape(H, W, 3)
        assert rgb.std() > 5  # a scene, not a blank buffer
        depth = rovers.sinks["depth", w].msg
        assert (depth.encoding, depth.width, depth.height, depth.step, depth.is_bigendian) == ("32FC1", W, H, 4 * W, 0)
        metres = np.frombuffer(bytes(depth.data), np.float32).reshape(H, W)
        assert np.isfinite(metres[H // 2 :]).all()  # the floor below the horizon; sky (+inf) above the walls
        assert 0.05 < np.nanmin(metres) and metres[np.isfinite(metres)].max() < 12  # a walled room
        info = rovers.sinks["info", w].msg
        assert (info.width, info.height, info.distortion_model) == (W, H, "plumb_bob")
        np.testing.assert_allclose(info.k, [fy, 0, (W - 1) / 2, 0, fy, (H - 1) / 2, 0, 0, 1], rtol=1e-9)
        assert info.header.frame_id == image.header.frame_id
        scan = rovers.sinks["scan", w].msg
        assert len(scan.ranges) == 360 and scan.header.frame_id == f"world_{w}/laser_frame"
        assert scan.range_min == pytest.approx(0.1) and scan.range_max == pytest.approx(12)
        assert scan.angle_min == pytest.approx(-math.pi, abs=1e-6) and scan.scan_time == pytest.approx(0.1)
        assert np.isfinite(scan.ranges).sum() > 300  # walls all round, within 12 m
        cloud = rovers.sinks["points", w].msg
        assert (cloud.height, cloud.width, cloud.point_step, cloud.row_step) == (3, 24, 12, 12 * 24)
        assert [(f.name, f.offset, f.datatype) for f in cloud.fields] == [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)]
        xyz = np.frombuffer(bytes(cloud.data), np.float32).reshape(3, 24, 3)
        assert cloud.header.frame_id == f"world_{w}/lidar" and np.isfinite(xyz).all()
        # the middle row lies in the lidar's plane, its points as far as the walls are
        assert np.abs(xyz[1, :, 2]).max() < 1e-4 and np.linalg.norm(xyz[1, :, :2], axis=1).min() > 0.2


def assert_sim_periods(gaps: np.ndarray, period: float) -> None:
    """Every gap a positive whole number of `period`s (to 1e-6 s), most of them exactly one."""
    periods = np.round(gaps / period)
    assert (periods >= 1).all(), gaps
    np.testing.assert_allclose(gaps, periods * period, atol=1e-6)
    assert (periods == 1).sum() > len(gaps) / 2, gaps


def test_stamps_are_sim_time(rovers):
    for w in range(NWORLD):
        rovers.wait(lambda w=w: len(rovers.sinks["image", w].history) >= 4, 20, f"four images of world {w}")
        stamps = [sim_time(m.header.stamp) for m in rovers.sinks["image", w].history]
        # frames a whole number of camera periods of sim time apart, whatever the wall clock did.
        # Mostly one period; a worker that stalls (seen: 0.3 s on the loaded 2-core CI machine)
        # finds only the newest frame in its world's camera block, so the others were never sent
        assert_sim_periods(np.diff(stamps), 1 / CAMERA_RATE)
        scans = [sim_time(m.header.stamp) for m in rovers.sinks["scan", w].history]
        assert_sim_periods(np.diff(scans), 0.1)  # the lidar's own update_rate
        # never ahead of /clock, once the clock message of the same period has arrived too
        # (the image and the clock travel apart: the image may come first)
        assert stamps[-1] > 0
        rovers.wait(lambda s=stamps[-1]: s <= sim_time(rovers.clock.msg.clock) + 1e-9, 5, "/clock at the last image")
        infos = {sim_time(m.header.stamp) for m in rovers.sinks["info", w].history}
        assert infos & set(stamps)  # CameraInfo carries its frame's stamp


def test_worlds_placed_differently_see_differently(rovers):
    before = [np.array(rovers.sinks["scan", w].msg.ranges) for w in range(NWORLD)]
    np.testing.assert_allclose(before[1], before[0], atol=1e-3)  # all start at the same pose

    def image(w: int) -> np.ndarray:
        return np.frombuffer(bytes(rovers.sinks["image", w].msg.data), np.uint8).astype(int)

    def turned() -> bool:
        a, b = (np.array(rovers.sinks["scan", w].msg.ranges) for w in (0, 1))
        scans = np.abs(np.nan_to_num(a - b, posinf=0, neginf=0)).max() > 0.5
        return scans and np.abs(image(1) - image(0)).mean() > 10

    # world 1 spins on the spot (wheel torques opposite), the others stand: its scan and its
    # image change, theirs do not
    rovers.publish_until(Float64MultiArray, "/world_1/commands", Float64MultiArray(data=[1.0, -1.0]), turned)
    assert np.abs(image(2) - image(0)).mean() < 1
    np.testing.assert_allclose(rovers.sinks["scan", 2].msg.ranges, rovers.sinks["scan", 0].msg.ranges, atol=1e-3)


def test_workers_publish_through_a_shared_memory_segment_sized_for_the_frames(rovers):
    """Fast DDS's default segment (512 KiB) is smaller than one 320x240 RGB-D frame pair: the
    workers' participants get one sized for their frames (ros_bridge/transport.py), and Fast
    DDS maps it."""
    workers = bridge_workers(rovers.proc.pid)
    assert len(workers) == 2
    for pid in workers.values():
        environ = dict(
            item.split("=", 1) for item in Path(f"/proc/{pid}/environ").read_text().split("\0") if "=" in item
        )
        profile = Path(environ[PROFILES_FILE])
        segment = int(re.search(r"<segment_size>(\d+)</segment_size>", profile.read_text()).group(1))
        assert segment >= MIN_SEGMENT
        mapped = []  # the worker's /dev/shm/fastrtps_* mappings, bytes
        for line in Path(f"/proc/{pid}/maps").read_text().splitlines():
            if "/dev/shm/fastrtps_" in line and "port" not in line:
                lo, hi = (int(x, 16) for x in line.split()[0].split("-"))
                mapped.append(hi - lo)
        assert max(mapped) >= segment, f"segment {segment} bytes; mapped {sorted(mapped)}"


# ---------------------------------------------------------------- on demand, bridge in process


class Client:
    """A node on `domain` in this process, spun on a thread."""

    def __init__(self, domain: int):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
        self.node = Node("sensor_test_client", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self.executor.spin, daemon=True)
        self._thread.start()

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def test_a_camera_nobody_subscribes_to_is_never_rendered(monkeypatch):
    from ros_bridge.bridge import BridgeOptions, start_bridge
    from ros_bridge.sensor_topics import SensorFeed

    domain = domain_id(75)
    for key, value in {**LOCALHOST, "ROS_DOMAIN_ID": str(domain)}.items():
        monkeypatch.setenv(key, value)
    sim = batchsim.make("rover", 2, "cpu", sensors={"sensors": {"camera_resolution": [16, 12], "camera_rate": 50}})
    sim.configure()
    sim.activate()
    loop = SimLoop(sim, control_rate=100.0, rtf=0.0)
    host = start_bridge(sim, loop, BridgeOptions(workers=0, clock=False))
    client = Client(domain)
    try:
        feed = next(p for p in loop.participants if isinstance(p, SensorFeed))

        def run(seconds: float, until=lambda: False) -> None:
            end = time.monotonic() + seconds
            while time.monotonic() < end and not until():
                loop.run_period()
                time.sleep(0.005)

        run(1.2)  # past two subscriber refreshes: nobody subscribes
        assert feed.sampler.produced == {"front_camera": 0, "base_scan": 0}

        got: list[Image] = []
        sub = client.node.create_subscription(Image, "/world_1/front_camera/image_raw", got.append, 10)
        run(20.0, until=lambda: len(got) >= 3)
        assert len(got) >= 3, "no images after subscribing"
        assert sim.sensors.wanted("front_camera").tolist() == [False, True]  # world 0: nobody subscribes
        assert feed.sampler.produced["base_scan"] == 0 and feed.sampler.produced["front_camera"] >= 3

        client.node.destroy_subscription(sub)
        run(20.0, until=lambda: not sim.sensors.wanted("front_camera").any())
        assert not sim.sensors.wanted("front_camera").any()
        run(0.1)  # a frame asked for in the period the subscriber left may still land
        produced = feed.sampler.produced["front_camera"]
        run(0.3)
        assert feed.sampler.produced["front_camera"] == produced
    finally:
        client.close()
        host.close()
        sim.shutdown()
        release_domain(domain)


# ---------------------------------------------------------------- shared memory


def _rss() -> int:
    """This process's resident memory, bytes (Linux)."""
    status = open("/proc/self/status").read()
    return int(next(line.split()[1] for line in status.splitlines() if line.startswith("VmRSS:"))) * 1024


@pytest.mark.parametrize("shared", [True, False], ids=["workers", "in-process"])
def test_camera_blocks_take_memory_only_where_written(shared):
    """The humanoid's three 320x240 cameras for 2048 worlds lay out 3.3 GB of image blocks;
    only the rows a sample writes may take memory."""
    from batchsim.memory import Layout, Memory
    from ros_bridge.protocol.sensor_blocks import SensorBlock
    from ros_bridge.sensor_topics import sensor_plan

    sim = batchsim.make("humanoid", 1, "cpu")
    plan = sensor_plan(sim)
    layout = Layout(plan.arrays(2048))
    assert layout.nbytes > 3e9
    before = _rss()
    memory = Memory.create(layout, shared=shared)
    try:
        assert _rss() - before < 64e6
        block = SensorBlock(memory, "cam0", ("rgb", "depth"))
        rgb = np.full((2, 240, 320, 3), 7, np.uint8)
        block.write(np.array([3, 2000]), 1.5, {"rgb": (np.array([3, 2000]), rgb)})
        rows, parts, stamps, data = block.read(0, 2048, np.zeros(2048, np.int64))
        assert rows.tolist() == [3, 2000] and parts.tolist() == [1, 1] and stamps.tolist() == [1.5, 1.5]
        assert (data["rgb"] == 7).all() and _rss() - before < 64e6 + 2 * data["rgb"].nbytes + data["depth"].nbytes
    finally:
        memory.close()


# ---------------------------------------------------------------- bulk framing


def test_framing_deserializes_to_the_messages():
    from batchsim.sensors.camera import Camera
    from batchsim.sensors.camera import CameraInfo as Info
    from ros_bridge.worker.sensor_messages import (
        camera_info_framing,
        image_framing,
        laser_scan_framing,
        point_cloud_framing,
    )

    k = (10.0, 0.0, 1.5, 0.0, 10.0, 1.0, 0.0, 0.0, 1.0)
    cam = Camera("c", 0, 4, 3, Info(4, 3, k, k[:3] + (0.0,) + k[3:6] + (0.0,) + k[6:] + (0.0,)), "f", "i", "d", "n")
    frames = ["a/f", "world_10/f"]  # rows of different lengths
    rgb = np.arange(36, dtype=np.uint8).reshape(3, 4, 3)
    for row, frame in enumerate(frames):
        msg = deserialize_message(image_framing(cam, frames, False, "t").payload(row, 7, 250, rgb), Image)
        assert (msg.header.frame_id, msg.header.stamp.sec, msg.header.stamp.nanosec) == (frame, 7, 250)
        assert bytes(msg.data) == rgb.tobytes() and msg.step == 12
        depth = np.full((3, 4), 1.25, np.float32)
        msg = deserialize_message(image_framing(cam, frames, True, "t").payload(row, 1, 2, depth), Image)
        assert np.frombuffer(bytes(msg.data), np.float32).tolist() == [1.25] * 12 and msg.encoding == "32FC1"
        msg = deserialize_message(camera_info_framing(cam, frames, "t").payload(row, 3, 4), CameraInfo)
        assert tuple(msg.k) == k and msg.header.stamp.sec == 3 and msg.header.frame_id == frame

    sim = batchsim.make("rover", 1, "cpu", sensors={"sensors": {"lidars": {"ring": {
        "site": "lidar", "horizontal": {"samples": 4, "min_angle": -1, "max_angle": 1},
        "vertical": {"samples": 2, "min_angle": -0.1, "max_angle": 0.1}}}}})  # fmt: skip
    ring, scan = sim.sensors.lidar("ring"), sim.sensors.lidar("base_scan")
    ranges = np.linspace(1, 2, 360, dtype=np.float32)
    ranges[5] = np.inf
    msg = deserialize_message(laser_scan_framing(scan, 10.0, ["w/l"], "t").payload(0, 5, 6, ranges), LaserScan)
    assert np.array_equal(np.array(msg.ranges, np.float32), ranges) and msg.scan_time == pytest.approx(0.1)
    r = np.array([[1, 2, np.inf, 4, 5, 6, 7, 8]], np.float32)
    pts = ring.points(r)[0]
    msg = deserialize_message(point_cloud_framing(ring, ["w/l"], "t").payload(0, 5, 6, pts), PointCloud2)
    xyz = np.frombuffer(bytes(msg.data), np.float32).reshape(2, 4, 3)
    assert np.isnan(xyz[0, 2]).all() and np.allclose(np.linalg.norm(xyz[1], axis=1), [5, 6, 7, 8])
