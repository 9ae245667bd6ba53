"""Cameras and lidars in an MCAP recording (issue 25: images opt-in), with the real components:
a `batchsim --record` rover fleet writes the file, mcap's reader and mcap-ros2-support's
decoder read it back; a live fleet's subscriber gets the messages the file holds. In this
process: the bulk framing of many rows, the recorder's sensor reader counting a sample it
missed, the default topic set without images, an unknown sensor topic as one line."""

from __future__ import annotations

import io
import os
import struct
import subprocess
import sys
import time
import types
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from conftest import need
from ros_fleet import LOCALHOST, Fleet, domain_id, release_domain

rclpy = need("rclpy")
need("mcap")
need("mcap_ros2")

from mcap.reader import make_reader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402
from rclpy.qos import QoSProfile  # noqa: E402
from rclpy.serialization import deserialize_message  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402

import batchsim  # noqa: E402
from batchsim import cli  # noqa: E402

pytestmark = pytest.mark.ros
W, H = 32, 24
CAMERA, RING, SCAN = 20.0, 20.0, 10.0  # Hz: --camera-rate, the ring's rate, the rover's lidar (its MJCF)
DURATION = 1.0
RING_YAML = """
sensors:
  lidars:
    ring: {site: lidar, horizontal: {samples: 24, min_angle: -3.1416, max_angle: 2.8798},
           vertical: {samples: 3, min_angle: -0.1, max_angle: 0.1}, range_min: 0.05, range_max: 20, rate: 20}
"""
SENSOR_TOPICS = ["front_camera/image_raw", "front_camera/depth/image_raw", "front_camera/camera_info", "scan", "points"]


def _rover_args(where: Path) -> list[str]:
    (where / "ring.yaml").write_text(RING_YAML)
    return ["--model", "rover", "--worlds", "3", "--camera-resolution", f"{W}x{H}", "--camera-rate", f"{CAMERA:g}",
            "--sensors", str(where / "ring.yaml")]  # fmt: skip


def _read(path: Path) -> dict[str, list[tuple[int, bytes, object]]]:
    """topic -> [(log time ns, CDR bytes, decoded)], in log time order; stamps checked = log times."""
    out: dict[str, list] = defaultdict(list)
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        for _schema, channel, message, decoded in reader.iter_decoded_messages():
            stamp = getattr(getattr(decoded, "header", None), "stamp", None)
            if stamp is not None:
                assert stamp.sec * 10**9 + stamp.nanosec == message.log_time, channel.topic
            out[channel.topic].append((message.log_time, message.data, decoded))
    return out


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Path, dict]:
    """Worlds 0 and 2 of 3 rovers: their camera's three topics, the 2D and the 3D lidar, and
    joint_states; 1 s of sim time, as fast as the recorder takes it (--rtf 0)."""
    where = tmp_path_factory.mktemp("sensors")
    path = where / "run.mcap"
    domain = domain_id(70)
    env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(domain), "PYTHONUNBUFFERED": "1"}
    args = [*_rover_args(where), "--controllers", "none", "--rtf", "0", "--duration", f"{DURATION:g}", "--quiet",
            "--record", str(path), "--record-worlds", "0,2", "--record-topics", ",".join([*SENSOR_TOPICS, "joint_states"])]  # fmt: skip
    try:
        with open(where / "log", "w") as log:
            proc = subprocess.run(
                [sys.executable, "-m", "batchsim.cli", *args], env=env, stdout=log, stderr=subprocess.STDOUT, timeout=180
            )
    finally:
        release_domain(domain)
    text = (where / "log").read_text()
    assert proc.returncode == 0, text
    assert f"messages in {path}" in text and "missed" not in text, text
    return path, _read(path)


def test_every_frame_and_scan_of_the_recorded_worlds_at_the_sensor_rate(recorded):
    _path, topics = recorded
    assert not any(t.startswith("/world_1/") for t in topics)  # --record-worlds 0,2
    for w in (0, 2):
        for topic, rate in (("front_camera/image_raw", CAMERA), ("front_camera/depth/image_raw", CAMERA),
                            ("front_camera/camera_info", CAMERA), ("scan", SCAN), ("points", RING)):  # fmt: skip
            times = np.array([t for t, _d, _m in topics[f"/world_{w}/{topic}"]]) * 1e-9
            # from the first sensor period, none left out: the renders in flight when the run ends too
            assert times[0] < 1 / rate and len(times) == round(DURATION * rate), (w, topic, times)
            np.testing.assert_allclose(np.diff(times), 1 / rate, atol=1e-6, err_msg=f"{w} {topic}")
        assert len(topics[f"/world_{w}/joint_states"]) == round(DURATION * 100)
        # one render per frame: the image, its depth and its camera_info share a stamp
        assert [t for t, *_ in topics[f"/world_{w}/front_camera/image_raw"]] == [
            t for t, *_ in topics[f"/world_{w}/front_camera/camera_info"]
        ]


def test_images_scans_and_clouds_read_back_as_the_bridge_lays_them_out(recorded):
    _path, topics = recorded
    for w in (0, 2):
        _t, _d, image = topics[f"/world_{w}/front_camera/image_raw"][-1]
        assert (image.encoding, image.width, image.height, image.step) == ("rgb8", W, H, 3 * W)
        assert image.header.frame_id == f"world_{w}/front_camera"
        rgb = np.frombuffer(bytes(image.data), np.uint8)
        assert rgb.size == 3 * W * H and rgb.std() > 5  # a scene, not a blank buffer
        _t, _d, depth = topics[f"/world_{w}/front_camera/depth/image_raw"][-1]
        assert (depth.encoding, depth.width, depth.height, depth.step) == ("32FC1", W, H, 4 * W)
        metres = np.frombuffer(bytes(depth.data), np.float32).reshape(H, W)
        assert np.isfinite(metres[H // 2 :]).all() and 0.05 < np.nanmin(metres) < 12  # the floor, the room
        _t, _d, info = topics[f"/world_{w}/front_camera/camera_info"][-1]
        assert (info.width, info.height, info.header.frame_id) == (W, H, image.header.frame_id)
        _t, _d, scan = topics[f"/world_{w}/scan"][-1]
        assert len(scan.ranges) == 360 and scan.scan_time == pytest.approx(1 / SCAN)
        assert np.isfinite(scan.ranges).mean() > 0.9  # a walled room
        _t, _d, cloud = topics[f"/world_{w}/points"][-1]
        assert (cloud.height, cloud.width, cloud.point_step, len(cloud.data)) == (3, 24, 12, 3 * 24 * 12)
        assert np.isfinite(np.frombuffer(bytes(cloud.data), np.float32)).mean() > 0.9


def test_a_live_recording_holds_what_a_subscriber_gets(tmp_path):
    """World 2 spins on the spot while worlds 0 and 2 are recorded at RTF 1: every image a
    subscriber of world 2 got is in the file, world 2's images change and
    world 0's do not, and a frame is missing from the file only where the recorder said so."""
    path = tmp_path / "live.mcap"
    args = [*_rover_args(tmp_path), "--record", str(path), "--record-worlds", "0,2",
            "--record-topics", "front_camera/image_raw,scan"]  # fmt: skip
    got: list[bytes] = []
    with Fleet(domain_id(70), args, tmp_path / "batchsim.log") as fleet:
        fleet.node.create_subscription(Image, "/world_2/front_camera/image_raw", got.append, QoSProfile(depth=100), raw=True)

        def image(k: int) -> np.ndarray:
            return np.frombuffer(got[k][-3 * W * H :], np.uint8).astype(int)

        fleet.wait(lambda: len(got) >= 2, 60, "world 2's images")
        fleet.publish_until(
            Float64MultiArray, "/world_2/commands", Float64MultiArray(data=[1.0, -1.0]),
            lambda: np.abs(image(-1) - image(0)).mean() > 10, what="world 2 turning",
        )  # fmt: skip
        time.sleep(0.3)
        assert fleet.close() == 0, (tmp_path / "batchsim.log").read_text()
    log = (tmp_path / "batchsim.log").read_text()
    topics = _read(path)
    recorded = {t: data for t, data, _m in topics["/world_2/front_camera/image_raw"]}
    matched = 0
    for data in got:
        sec, nanosec = struct.unpack_from("<iI", data, 4)
        if sec * 10**9 + nanosec in recorded:
            # the same message (CDR's padding bytes are whatever each process's serializer left there)
            assert deserialize_message(recorded[sec * 10**9 + nanosec], Image) == deserialize_message(data, Image)
            matched += 1
    assert matched >= max(3, len(got) - 2), (matched, len(got))  # the last ones may follow the file's end
    first0, last0 = (np.frombuffer(bytes(topics["/world_0/front_camera/image_raw"][k][2].data), np.uint8).astype(int) for k in (0, -1))
    last2 = np.frombuffer(bytes(topics["/world_2/front_camera/image_raw"][-1][2].data), np.uint8).astype(int)
    assert np.abs(last0 - first0).mean() < 1 and np.abs(last2 - last0).mean() > 10
    missed = int(log.split(" camera or lidar samples missed")[0].rsplit("; ", 1)[-1]) if "samples missed" in log else 0
    gaps = 0
    for w in (0, 2):
        for topic, rate in (("front_camera/image_raw", CAMERA), ("scan", SCAN)):
            times = np.array([t for t, *_ in topics[f"/world_{w}/{topic}"]]) * 1e-9
            gaps += int(np.round(np.diff(times) * rate).sum()) - (len(times) - 1)
    assert gaps == missed, log


def test_the_bulk_framing_lays_out_what_payload_gives_per_row():
    from batchsim.sensors.camera import Camera
    from batchsim.sensors.camera import CameraInfo as Info
    from ros_bridge.worker.sensor_messages import camera_info_framing, image_framing

    k = (10.0, 0.0, 1.5, 0.0, 10.0, 1.0, 0.0, 0.0, 1.0)
    cam = Camera("c", 0, 4, 3, Info(4, 3, k, k[:3] + (0.0,) + k[3:6] + (0.0,) + k[6:] + (0.0,)), "f", "i", "d", "n")
    frames = ["a/f", "world_10/f", "b/f", "world_2/camera"]  # three lengths of frame id
    rows = np.array([3, 1, 0])
    for framing, data in (
        (image_framing(cam, frames, False, "t"), np.arange(4 * 36, dtype=np.uint8).reshape(4, 3, 4, 3)[rows]),
        (image_framing(cam, frames, True, "t"), np.random.default_rng(0).random((3, 3, 4), dtype=np.float32)),
        (camera_info_framing(cam, frames, "t"), None),
    ):
        seen = []
        for where, block in framing.block(rows, 7, 250, data):
            for i, message in zip(where.tolist(), block, strict=True):
                assert message.tobytes() == framing.payload(int(rows[i]), 7, 250, b"" if data is None else data[i].tobytes())
                seen.append(i)
        assert sorted(seen) == [0, 1, 2]


def _sensor_recording(nworld: int):
    """A SensorRecording of a rover's 8x6 camera (image_raw) and 2D lidar over plain arrays."""
    from ros_bridge.protocol.sensor_blocks import WANT_RGB
    from ros_bridge.recording import RecordSpec
    from ros_bridge.sensor_topics import sensor_plan
    from ros_bridge.worker.mcap_file import BlockWriter
    from ros_bridge.worker.sensor_recording import SensorRecording

    sim = batchsim.make("rover", 1, "cpu", sensors={"sensors": {"cameras": {"front_camera": {"width": 8, "height": 6}}}})
    sensors = sensor_plan(sim)
    worlds = tuple(range(nworld))
    spec = RecordSpec((), False, False, False, False, worlds, (), (), sensors=(WANT_RGB, WANT_RGB))
    memory = {name: np.zeros(shape, dtype) for name, shape, dtype in [*sensors.arrays(nworld), *spec.arrays(1)]}
    plan = types.SimpleNamespace(recording=spec, sensors=sensors, namespaces=[f"world_{w}" for w in worlds])
    stream = io.BytesIO()
    writer = BlockWriter(stream)
    writer.start(profile="ros2", library="test")
    schema = writer.register_schema(name="sensor_msgs/msg/Image", encoding="ros2msg", data=b"")

    def channel(topic: str, msg_type: str) -> int:
        return writer.register_channel(topic=topic, message_encoding="cdr", schema_id=schema, metadata={})

    return SensorRecording(plan, memory, channel, writer), memory, writer, stream


def test_a_worker_publishes_each_new_sample_once_and_counts_the_ones_overwritten_before_it_looked():
    """A camera's block holds each world's newest sample only: what a busy worker never got is
    counted per world and topic, for /diagnostics (`missed front_camera/image_raw`), where a
    subscriber listens; before, it was lost without a word."""
    from ros_bridge.protocol.sensor_blocks import SensorBlock
    from ros_bridge.sensor_topics import sensor_plan
    from ros_bridge.worker.sensors import SensorPublishers

    class Publisher:
        def __init__(self):
            self.sent = 0

        def publish(self, payload) -> None:
            self.sent += 1

        def get_subscription_count(self) -> int:
            return 1

    class Node:
        publishers: dict[str, Publisher] = {}

        def create_publisher(self, msg_type, topic, qos, **kwargs):
            return self.publishers.setdefault(topic, Publisher())

    sim = batchsim.make("rover", 1, "cpu", sensors={"sensors": {"cameras": {"front_camera": {"width": 8, "height": 6}}}})
    plan = sensor_plan(sim)
    memory = {name: np.zeros(shape, dtype) for name, shape, dtype in plan.arrays(6)}
    missed: list[tuple[str, list[int], list[int]]] = []
    node = Node()
    worker = SensorPublishers(node, QoSProfile(depth=1), memory, plan, 2, 6, [f"world_{w}" for w in range(2, 6)], True,
                              lambda topic, rows, counts: missed.append((topic, rows.tolist(), counts.tolist())))  # fmt: skip
    worker.refresh()  # every topic subscribed
    block = SensorBlock(memory, "cam0", ("rgb", "depth"))
    rgb = np.zeros((6, 6, 8, 3), np.uint8)
    everyone = np.arange(6)
    block.write(everyone, 0.05, {"rgb": (everyone, rgb)})
    worker.publish()
    image = node.publishers["/world_3/front_camera/image_raw"]
    assert image.sent == 1 and not missed
    block.write(everyone, 0.10, {"rgb": (everyone, rgb)})  # worlds 2-5: overwritten unread
    block.write(everyone[3:], 0.15, {"rgb": (everyone[3:], rgb[3:])})  # worlds 3-5 again
    block.write(everyone[3:], 0.20, {"rgb": (everyone[3:], rgb[3:])})  # ... and again
    worker.publish()
    assert image.sent == 2  # the newest only
    counted = {topic: (rows, counts) for topic, rows, counts in missed}
    assert counted["front_camera/image_raw"] == ([1, 2, 3], [2, 2, 2])  # this worker's rows: worlds 3-5, 2 each
    assert counted["front_camera/camera_info"] == ([1, 2, 3], [2, 2, 2])  # it goes with each frame
    assert "front_camera/depth/image_raw" not in counted  # no depth in these samples: none would have gone
    assert "scan" not in counted  # the lidar wrote nothing
    worker.publish()
    assert len(missed) == len(counted) and image.sent == 2  # nothing new: nothing published or counted


def test_a_worker_busy_with_camera_frames_still_takes_every_scan():
    """On the H100, 1024 rovers' workers missed ~19 % of the 10 Hz scans: a tick publishing 128
    worlds' RGB-D frames outlasted the lidar's period, and its block keeps the newest scan only.
    The worker now looks at the lidars' blocks every POLL_EVERY camera messages. Here two scans
    are written while one round of frames goes out: all three scans are published, none missed
    (before: the worker took the lidar's block once, after the frames, and 2 of the 3 were lost)."""
    from ros_bridge.protocol.sensor_blocks import SensorBlock
    from ros_bridge.sensor_topics import sensor_plan
    from ros_bridge.worker.sensors import POLL_EVERY, SensorPublishers

    nworld = 40
    sim = batchsim.make("rover", 1, "cpu", sensors={"sensors": {"cameras": {"front_camera": {"width": 8, "height": 6}}}})
    plan = sensor_plan(sim)
    memory = {name: np.zeros(shape, dtype) for name, shape, dtype in plan.arrays(nworld)}
    camera, lidar = SensorBlock(memory, "cam0", ("rgb", "depth")), SensorBlock(memory, "lid0", ("ranges",))
    everyone = np.arange(nworld)
    ranges = np.ones(memory["lid0.ranges"].shape, memory["lid0.ranges"].dtype)
    sent = {"frames": 0, "scans": 0}

    class Publisher:
        def __init__(self, topic: str):
            self.kind = "scans" if topic.endswith("/scan") else "frames"

        def publish(self, payload) -> None:
            sent[self.kind] += 1
            if self.kind == "frames" and sent["frames"] in (20, 40):  # the loop writes scans meanwhile
                lidar.write(everyone, 0.1 * sent["frames"], {"ranges": (everyone, ranges)})

        def get_subscription_count(self) -> int:
            return 1

    class Node:
        def create_publisher(self, msg_type, topic, qos, **kwargs):
            return Publisher(topic)

    missed = []
    worker = SensorPublishers(Node(), QoSProfile(depth=1), memory, plan, 0, nworld, [f"world_{w}" for w in everyone], True,
                              lambda topic, rows, counts: missed.append((topic, int(counts.sum()))))  # fmt: skip
    worker.refresh()
    lidar.write(everyone, 0.0, {"ranges": (everyone, ranges)})
    camera.write(everyone, 0.0, {"rgb": (everyone, np.zeros((nworld, 6, 8, 3), np.uint8))})
    worker.publish()
    assert sent["frames"] == 2 * nworld > 40 + POLL_EVERY  # image_raw and camera_info: the scans came while they went
    worker.publish()
    assert sent["scans"] == 3 * nworld and not missed, (sent, missed)


def test_the_recorder_takes_each_new_sample_once_and_counts_the_ones_overwritten_before_it_looked():
    from ros_bridge.protocol.sensor_blocks import SensorBlock

    recording, memory, writer, stream = _sensor_recording(12)
    block = SensorBlock(memory, "cam0", ("rgb", "depth"))
    rgb = np.arange(12 * 6 * 8 * 3, dtype=np.uint32).astype(np.uint8).reshape(12, 6, 8, 3)
    everyone = np.arange(12)
    block.write(everyone, 0.05, {"rgb": (everyone, rgb)})
    recording.take()
    recording.take()  # nothing new: nothing written twice
    assert recording.messages == 12 and recording.missed == 0
    block.write(everyone[:4], 0.10, {"rgb": (everyone[:4], rgb[:4])})
    block.write(everyone[:4], 0.15, {"rgb": (everyone[:4], rgb[:4])})  # worlds 0-3: 0.10 overwritten
    recording.take()
    assert recording.messages == 16 and recording.missed == 4
    assert np.array_equal(memory["rec.sensors.seen"][:, 0], block.seq)  # what --rtf 0 waits on
    assert "4 camera or lidar samples missed" in recording.closing()
    writer.finish()
    stream.seek(0)
    stamps = defaultdict(list)
    for _s, channel, message in make_reader(stream).iter_messages():
        stamps[channel.topic].append(message.log_time)
        assert len(message.data) > 6 * 8 * 3
    assert stamps["/world_3/front_camera/image_raw"] == [50_000_000, 150_000_000]
    assert stamps["/world_11/front_camera/image_raw"] == [50_000_000]


def test_the_default_topic_set_records_no_images():
    from ros_bridge.options import RecordOptions
    from ros_bridge.recording import record_spec
    from ros_bridge.sensor_topics import sensor_plan

    sensors = sensor_plan(batchsim.make("rover", 1, "cpu"))
    spec = record_spec(RecordOptions(path="x.mcap"), [], [], None, True, 2, sensors)
    assert spec.sensors == () and not any(name.startswith("rec.sensors") for name, *_ in spec.arrays(1))
    chosen = record_spec(RecordOptions(topics=("front_camera/depth/image_raw", "/scan")), [], [], None, True, 2, sensors)
    assert chosen.sensors == (2, 1) and chosen.clock is False


def test_an_unknown_sensor_topic_is_one_line(capsys, monkeypatch):
    domain = domain_id(70)
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    try:
        args = ["--model", "rover", "--worlds", "2", "--controllers", "none", "--record-topics", "front_camera/imag_raw"]
        assert cli.main(args) == 2
    finally:
        release_domain(domain)
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith("batchsim: error: --record-topics names 'front_camera/imag_raw', which this fleet does not publish")
    assert "front_camera/image_raw" in err and "scan" in err
