"""A bridge worker's camera and lidar topics (ros_bridge/sensor_topics.py says which, and how
images and scans reach it).

Publishers are created on request: the worker's graph scan calls `requested(topic)` for
each topic in the graph, and a topic of ours that someone subscribes to gets its publisher
(`--all-topics`: every one at start). The worker calls `refresh()` when it re-reads subscriber counts
(lazy publishing): the topics with a subscriber become want bits in shared memory, which
the physics side turns into rendering and scanning for those worlds only. It calls
`publish()` on every tick: each world's sample that is new since the last tick (its seq
moved) is published once, as CDR bytes built in bulk (ros_bridge/worker/sensor_messages.py),
stamped with the sim time of the sample.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import CameraInfo, Image, LaserScan, PointCloud2

from ros_bridge.naming import topic_name
from ros_bridge.protocol.sensor_blocks import WANT_DEPTH, WANT_INFO, WANT_RGB, SensorBlock
from ros_bridge.sensor_topics import SensorPlan
from ros_bridge.worker.messages import stamp_of
from ros_bridge.worker.sensor_messages import (
    Framing,
    camera_info_framing,
    image_framing,
    laser_scan_framing,
    point_cloud_framing,
)


def under(namespaces: Sequence[str], name: str) -> list[str]:
    """`name` under each namespace, without a leading `/`: a configured topic or frame that is
    absolute (mujoco_ros2_control's `/camera/color/image_raw`) goes under the world's too."""
    return [topic_name(ns, name)[1:] for ns in namespaces]


class _Topic:
    """One topic of one camera or lidar over this worker's worlds: publishers (None until
    someone subscribes), the rows with a subscriber, and its framing (laid out when first
    published)."""

    def __init__(self, msg_type: type, topics: list[str], framing: Any):
        self.msg_type = msg_type
        self.publishers: list[Any] = [None] * len(topics)
        self.topics = topics
        self.subscribed = np.zeros(len(topics), bool)
        self._make = framing
        self._framing: Framing | None = None

    @property
    def framing(self) -> Framing:
        if self._framing is None:
            self._framing = self._make()
        return self._framing

    def refresh(self) -> np.ndarray:
        self.subscribed = np.array([p is not None and p.get_subscription_count() > 0 for p in self.publishers], bool)
        return self.subscribed


class SensorPublishers:
    """The camera and lidar topics of worlds [lo, hi).

    Args:
      node: the worker's node.
      qos: every topic's QoS.
      memory: the shared arrays.
      plan: the fleet's sensors.
      lo, hi: this worker's worlds.
      namespaces: (hi - lo,) their namespaces.
      all_topics: create every publisher now, not when a subscriber appears.

    Attributes:
      published: messages published so far.
    """

    def __init__(
        self,
        node: Node,
        qos: QoSProfile,
        memory: Any,
        plan: SensorPlan,
        lo: int,
        hi: int,
        namespaces: Sequence[str],
        all_topics: bool = False,
    ):
        self.lo, self.hi = lo, hi
        self.want = memory["sensors.want"]
        self.published = 0
        n = hi - lo
        self.cameras: list[tuple[SensorBlock, np.ndarray, _Topic, _Topic, _Topic]] = []
        for k, ct in enumerate(plan.cameras):
            cam = ct.camera
            frames = under(namespaces, cam.frame_id)

            def topic(name: str) -> list[str]:
                return ["/" + t for t in under(namespaces, name)]

            image = topic(cam.image_topic)
            depth = topic(cam.depth_topic)
            info = topic(cam.info_topic)
            self.cameras.append(
                (
                    SensorBlock(memory, f"cam{k}", ("rgb", "depth")),
                    np.zeros(n, np.int64),
                    _Topic(Image, image, lambda c=cam, f=frames, t=image[0]: image_framing(c, f, False, t)),
                    _Topic(Image, depth, lambda c=cam, f=frames, t=depth[0]: image_framing(c, f, True, t)),
                    _Topic(CameraInfo, info, lambda c=cam, f=frames, t=info[0]: camera_info_framing(c, f, t)),
                )
            )
        self.lidars: list[tuple[SensorBlock, np.ndarray, _Topic, Any]] = []
        for k, lt in enumerate(plan.lidars):
            ld = lt.lidar
            frames = under(namespaces, ld.frame_id)
            names = ["/" + t for t in under(namespaces, ld.topic)]
            if ld.is_3d:
                t = _Topic(PointCloud2, names, lambda d=ld, f=frames, t=names[0]: point_cloud_framing(d, f, t))
            else:
                t = _Topic(
                    LaserScan, names, lambda d=ld, r=lt.rate, f=frames, t=names[0]: laser_scan_framing(d, r, f, t)
                )
            self.lidars.append((SensorBlock(memory, f"lid{k}", ("ranges",)), np.zeros(n, np.int64), t, ld))
        # topic -> (its _Topic, row): publishers are created once a subscriber shows up in the
        # graph (a fleet of thousands of worlds would otherwise hold 3 endpoints per camera and world)
        self.node, self.qos = node, qos
        self._pending: dict[str, tuple[_Topic, int]] = {}
        topics = [t for c in self.cameras for t in c[2:]] + [lid[2] for lid in self.lidars]
        for t in topics:
            for row, name in enumerate(t.topics):
                self._pending[name] = (t, row)
        if all_topics:
            for name in list(self._pending):
                self.create(name)

    def create(self, topic: str) -> bool:
        """Create the publisher of `topic` if it is one of ours still waiting; True if it was."""
        hit = self._pending.pop(topic, None)
        if hit is None:
            return False
        t, row = hit
        t.publishers[row] = self.node.create_publisher(t.msg_type, topic, self.qos)
        return True

    def requested(self, topic: str) -> bool:
        """The worker's graph scan: `topic` is ours and someone subscribes: its publisher is created."""
        return topic in self._pending and self.node.count_subscribers(topic) > 0 and self.create(topic)

    def refresh(self) -> None:
        """Subscriber counts -> this worker's rows of the want bits."""
        want = np.zeros((self.hi - self.lo, self.want.shape[1]), np.uint8)
        for s, (_, _, image, depth, info) in enumerate(self.cameras):
            want[:, s] = image.refresh() * WANT_RGB | depth.refresh() * WANT_DEPTH | info.refresh() * WANT_INFO
        for s, (_, _, topic, _) in enumerate(self.lidars, start=len(self.cameras)):
            want[:, s] = topic.refresh() * WANT_RGB
        self.want[self.lo : self.hi] = want

    def publish(self) -> None:
        """Publish every sample written since the last call, once, where someone subscribes."""
        lo, hi = self.lo, self.hi
        for block, seen, image, depth, info in self.cameras:
            rows, parts, time, data = block.read(lo, hi, seen)
            for i, r in enumerate(rows.tolist()):
                sec, nanosec = stamp_of(float(time[i]))
                if image.subscribed[r] and parts[i] & WANT_RGB:
                    image.publishers[r].publish(image.framing.payload(r, sec, nanosec, data["rgb"][i]))
                    self.published += 1
                if depth.subscribed[r] and parts[i] & WANT_DEPTH:
                    depth.publishers[r].publish(depth.framing.payload(r, sec, nanosec, data["depth"][i]))
                    self.published += 1
                if info.subscribed[r]:
                    info.publishers[r].publish(info.framing.payload(r, sec, nanosec))
                    self.published += 1
        for block, seen, topic, ld in self.lidars:
            rows, _, time, data = block.read(lo, hi, seen)
            if not rows.size:
                continue
            values = ld.points(data["ranges"]) if ld.is_3d else data["ranges"]
            for i, r in enumerate(rows.tolist()):
                if topic.subscribed[r]:
                    sec, nanosec = stamp_of(float(time[i]))
                    topic.publishers[r].publish(topic.framing.payload(r, sec, nanosec, values[i]))
                    self.published += 1
