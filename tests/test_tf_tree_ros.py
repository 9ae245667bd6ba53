"""Every frame id a fleet's messages name is in its world's tf tree (issue 47): the frames of the
camera images and camera_info (REP 103 optical frames), the lidar's scan, the IMU and the wrist's
force-torque sensor, odometry's, the broadcasters' and tf's own, each walked up through /tf and
/tf_static to the fleet's `world`. Before, /tf carried bodies only, and RViz could place none of
the sensor messages.

The fleet: examples/fleets/arm_and_rover.yaml (an arm and a rover sharing each world: the rover's
camera, lidar and IMU site, the arm's wrist force-torque sensor), two worlds, every topic
created at start (--all-topics), in a batchsim subprocess over real DDS. Domain 64.
"""

from __future__ import annotations

import importlib
import time
from pathlib import Path

import pytest
from conftest import need
from ros_fleet import Fleet, domain_id

rclpy = need("rclpy")
pytestmark = pytest.mark.ros

FLEET = Path(__file__).parent.parent / "examples" / "fleets" / "arm_and_rover.yaml"


def _message_type(name: str) -> type:
    """`sensor_msgs/msg/Image` -> its class."""
    package, _, cls = name.split("/")
    return getattr(importlib.import_module(f"{package}.msg"), cls)


def _root_of(frame: str, parents: dict[str, str]) -> str:
    seen = set()
    while frame in parents and frame not in seen:
        seen.add(frame)
        frame = parents[frame]
    return frame


def test_every_frame_id_a_world_publishes_is_in_its_tf_tree(tmp_path):
    from rclpy.qos import DurabilityPolicy, QoSProfile
    from tf2_msgs.msg import TFMessage

    args = ["--fleet", str(FLEET), "--worlds", "2", "--controllers", "default", "--all-topics",
            "--camera-resolution", "32x24"]  # fmt: skip
    with Fleet(domain_id(64), args, tmp_path / "batchsim.log") as fleet:
        fleet.wait_started()
        parents: dict[str, str] = {}

        def on_tf(msg) -> None:
            for t in msg.transforms:
                parents[t.child_frame_id] = t.header.frame_id

        fleet.node.create_subscription(TFMessage, "/tf", on_tf, 10)
        latched = QoSProfile(depth=100, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        fleet.node.create_subscription(TFMessage, "/tf_static", on_tf, latched)
        stamped: dict[str, set[str]] = {}  # topic -> the frame ids its messages name
        deadline = time.monotonic() + 30
        subscribed: set[str] = set()
        kinds: set[str] = set()
        while time.monotonic() < deadline:  # the topics of world 1, as they appear
            for topic, types in fleet.node.get_topic_names_and_types():
                if not topic.startswith("/world_1/") or "/_action/" in topic or topic in subscribed or not types:
                    continue
                cls = _message_type(types[0])
                if "header" not in cls.get_fields_and_field_types() or not fleet.node.get_publishers_info_by_topic(topic):
                    continue  # no stamp, or an input (batchsim subscribes)
                subscribed.add(topic)

                def sink(msg, topic=topic) -> None:
                    frames = stamped.setdefault(topic, set())
                    frames.add(msg.header.frame_id)
                    if getattr(msg, "child_frame_id", ""):
                        frames.add(msg.child_frame_id)

                fleet.node.create_subscription(cls, topic, sink, 10)
                kinds.add(types[0])
            if len(stamped) >= len(subscribed) > 5 and time.monotonic() > deadline - 20:
                break
            time.sleep(0.5)
        missing = sorted(subscribed - set(stamped))
        assert not missing, f"no message on {missing}"
        assert {"sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo", "sensor_msgs/msg/LaserScan",
                "geometry_msgs/msg/WrenchStamped", "nav_msgs/msg/Odometry"} <= kinds, sorted(subscribed)  # fmt: skip
        lost = {}
        for topic, frames in stamped.items():
            for frame in frames - {""}:  # no frame (a JointState's): nothing to place
                assert frame.startswith("world_1/") or frame == "world", (topic, frame)
                if _root_of(frame, parents) != "world":
                    lost[topic] = frame
        assert not lost, f"frames in no tree (topic: frame): {lost}"
        assert all(_root_of(child, parents) == "world" for child in parents)
        # the camera's image frame is an optical frame: z along the camera's view (the rover's +x)
        optical = next(f for t, fs in stamped.items() if t.endswith("image_raw") for f in fs)
        assert optical == "world_1/rover/front_camera"
        scan = next(fs for t, fs in stamped.items() if t.endswith("/scan"))
        assert scan == {"world_1/rover/lidar"}, scan  # the lidar's site
