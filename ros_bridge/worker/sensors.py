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

import functools
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import CameraInfo, Image, LaserScan, PointCloud2

from batchsim.stamps import stamp_of
from ros_bridge.naming import topic_name
from ros_bridge.protocol.sensor_blocks import PART_BITS, WantWriter, gaps
from ros_bridge.sensor_topics import SensorPlan, SensorTopic, TopicKind
from ros_bridge.worker.sensor_messages import Framing, topic_framing

POLL_EVERY = 16  # camera messages between two looks at the lidars' blocks (SensorPublishers.publish)


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
      count_missed: told (topic, rows, counts) of the samples subscribed rows never got: each
        block holds a world's newest sample only (Diagnostics.missed).
      on_matched: called (on the executor's thread) when a subscriber of a topic comes or goes,
        so the worker reads the counts at once rather than at its next SUBSCRIBER_REFRESH: the
        first frame follows a subscription by a camera period and a render.

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
        count_missed: Callable[[str, np.ndarray, np.ndarray], None] | None = None,
        on_matched: Callable[[], None] | None = None,
    ):
        self.lo, self.hi, self.plan = lo, hi, plan
        self._events = PublisherEventCallbacks(matched=lambda info: on_matched()) if on_matched else None
        self.want = WantWriter(memory, lo, hi)
        self.published = 0
        self.count_missed = count_missed
        n = hi - lo
        # per sensor (`sensors.want` column): its block, each row's last seq published, its
        # topics (SensorPlan.topics(): name, kind, want bit, block part) with their publishers
        self.blocks = [plan.block(memory, s) for s in range(plan.nsensor)]
        self.seen = [np.zeros(n, np.int64) for _ in self.blocks]
        self.topics: list[list[tuple[SensorTopic, _Topic]]] = [[] for _ in self.blocks]
        for t in plan.topics():
            source, rate = plan.source(t.sensor)
            names = ["/" + name for name in under(namespaces, t.name)]
            make = functools.partial(topic_framing, t.kind, source, rate, under(namespaces, source.frame_id), names[0])
            self.topics[t.sensor].append((t, _Topic(_MSG_TYPES[t.kind], names, make)))
        # topic -> (its _Topic, row): publishers are created once a subscriber shows up in the
        # graph (a fleet of thousands of worlds would otherwise hold 3 endpoints per camera and world)
        self.node, self.qos = node, qos
        self._pending: dict[str, tuple[_Topic, int]] = {}
        for t in (topic for topics in self.topics for _, topic in topics):
            for row, name in enumerate(t.topics):
                self._pending[name] = (t, row)
        if all_topics:
            for name in list(self._pending):
                self.create(name)
        lidar = [any(t.kind in (TopicKind.SCAN, TopicKind.CLOUD) for t, _ in topics) for topics in self.topics]
        self._lidars = [s for s, is_lidar in enumerate(lidar) if is_lidar]
        self._cameras = [s for s, is_lidar in enumerate(lidar) if not is_lidar]

    def create(self, topic: str) -> bool:
        """Create the publisher of `topic` if it is one of ours still waiting; True if it was."""
        hit = self._pending.pop(topic, None)
        if hit is None:
            return False
        t, row = hit
        t.publishers[row] = self.node.create_publisher(t.msg_type, topic, self.qos, event_callbacks=self._events)
        return True

    def requested(self, topic: str) -> bool:
        """The worker's graph scan: `topic` is ours and someone subscribes: its publisher is created."""
        return topic in self._pending and self.node.count_subscribers(topic) > 0 and self.create(topic)

    def refresh(self) -> None:
        """Subscriber counts -> this worker's rows of the want bits."""
        want = np.zeros((self.hi - self.lo, self.want.nsensor), np.int64)
        for s, topics in enumerate(self.topics):
            for t, topic in topics:
                want[:, s] |= topic.refresh() * t.want
        self.want.put(want)

    def publish(self) -> None:
        """Publish every sample written since the last call, once, where someone subscribes:
        a topic with a payload where its part was written, CameraInfo with its camera's frames.
        The lidars' blocks are looked at again every POLL_EVERY camera messages: a tick that
        publishes a worker's RGB-D frames (69 MB for 128 rovers at 320x240) outlasts a 10 Hz
        lidar's period, and its block holds each world's newest scan only."""
        for s in self._lidars:
            self._publish_sensor(s)
        for s in self._cameras:
            self._publish_sensor(s, between=self._lidars)

    def _publish_sensor(self, s: int, between: Sequence[int] = ()) -> None:
        """Sensor `s`'s new samples; `between`: sensors published again every POLL_EVERY messages."""
        block, seen, topics = self.blocks[s], self.seen[s], self.topics[s]
        before = seen.copy()
        rows, parts, time, data = block.read(self.lo, self.hi, seen)
        if not rows.size:
            return
        lost = gaps(before[rows], seen[rows])
        stamps = [stamp_of(float(x)) for x in time]
        sent = 0
        for t, topic in topics:
            if self.count_missed is not None and lost.any():  # those it would have published, as this one
                hit = (lost > 0) & topic.subscribed[rows] & ((parts & PART_BITS[t.part]) != 0 if t.part else True)
                if hit.any():
                    self.count_missed(t.name, rows[hit], lost[hit])
            values = data[t.part] if t.part is not None else None
            if t.kind is TopicKind.CLOUD:
                values = self.plan.source(s)[0].points(values)
            for i, r in enumerate(rows.tolist()):
                if not topic.subscribed[r] or (values is not None and not parts[i] & PART_BITS[t.part]):
                    continue
                extra = () if values is None else (values[i],)
                topic.publishers[r].publish(topic.framing.payload(r, *stamps[i], *extra))
                self.published += 1
                sent += 1
                if between and sent % POLL_EVERY == 0:
                    for other in between:
                        self._publish_sensor(other)


_MSG_TYPES = {
    TopicKind.IMAGE: Image,
    TopicKind.DEPTH: Image,
    TopicKind.INFO: CameraInfo,
    TopicKind.SCAN: LaserScan,
    TopicKind.CLOUD: PointCloud2,
}

