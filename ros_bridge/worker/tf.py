"""tf, tf_static and robot_description for a worker's worlds, built in bulk.

Frame names follow the fleet's convention (README, "tf and robot_description"): every
frame of world `<ns>` is `<ns>/<link>` (the link names of its robot_description), and
each world's root frame hangs from the fleet's fixed frame (`world`) by an identity
transform, so one tf tree holds every world and RViz shows them all in `world`:

- `/tf` (one TFMessage per worker and publish period: every moving transform of its
  worlds) and `/tf_static` (transient local: every world's fixed transforms, once);
- `/<ns>/tf` and `/<ns>/tf_static`: the same transforms of one world alone, for a robot
  stack that listens to its own namespace (nav2's multi-robot setups remap tf so);
- `/<ns>/robot_description` (std_msgs/String, transient local): the URDF, whose link
  names are the frames without their prefix (RViz's RobotModel takes `<ns>` as TF Prefix);
- `/<ns>/<robot>/robot_description` (likewise) in a world of several robots: each robot's URDF,
  its links that robot's bodies, as tf names them `<ns>/<robot>/<body>`;
- `/<ns>/mujoco_robot_description` (likewise): the MJCF the simulation compiled, as
  mujoco_ros2_control publishes the one it generates from a URDF.

Per-world topics exist only once somebody subscribes (found by the worker's graph scan);
the fleet-wide ones from the start. Moving transforms are computed here, for this worker's
worlds, from one snapshot channel of body poses (TfSpec.moving_transforms), and filled into
serialized templates, as ros_bridge/worker/messages.py does for every other message.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from std_msgs.msg import String
from tf2_msgs.msg import TFMessage

from ros_bridge.naming import frame, topic_name
from ros_bridge.tf_plan import TfSpec
from ros_bridge.worker.messages import (
    locate_markers,
    locate_stamps,
    set_stamp_marker,
    stamp_bytes,
    value_markers,
)

RSP = "robot_state_publisher"  # the node that publishes /robot_description in a ros2_control stack
#: tf2_ros's DynamicBroadcasterQoS and StaticBroadcasterQoS
DYNAMIC_QOS = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
STATIC_QOS = QoSProfile(
    depth=1,
    history=HistoryPolicy.KEEP_LAST,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)


def _transform(parent: str, child: str, value: Any) -> TransformStamped:
    t = TransformStamped()
    set_stamp_marker(t.header.stamp)
    t.header.frame_id, t.child_frame_id = parent, child
    tr, rot = t.transform.translation, t.transform.rotation
    tr.x, tr.y, tr.z, rot.x, rot.y, rot.z, rot.w = (float(v) for v in value)
    return t


class TfTemplate:
    """The moving transforms of some worlds as one serialized TFMessage, filled in bulk."""

    def __init__(self, spec: TfSpec, namespaces: list[str]):
        moving = spec.all_moving
        markers = value_markers(7 * len(moving) * len(namespaces)).reshape(len(namespaces), len(moving), 7)
        msg = TFMessage()
        for w, ns in enumerate(namespaces):
            for k, (parent, child) in enumerate(moving):
                msg.transforms.append(_transform(frame(ns, parent), frame(ns, child), markers[w, k]))
        data = bytes(serialize_message(msg))
        self.buf = np.frombuffer(data, np.uint8).copy()
        at = locate_markers(data, markers.size, "tf")
        self.value_bytes = (at[:, None] + np.arange(8)).reshape(-1)
        self.stamp_bytes = (locate_stamps(data)[:, None] + np.arange(8)).reshape(-1)

    def fill(self, values: np.ndarray, sec: int, nanosec: int) -> bytes:
        """values: (nworld of the template, 7 * nmoving) float64."""
        self.buf[self.value_bytes] = np.ascontiguousarray(values, np.float64).view(np.uint8).reshape(-1)
        self.buf[self.stamp_bytes] = np.tile(stamp_bytes(sec, nanosec), len(self.stamp_bytes) // 8)
        return self.buf.tobytes()


def static_message(
    spec: TfSpec, namespaces: list[str], worlds: Sequence[int], sec: int = 0, nanosec: int = 0
) -> TFMessage:
    """Every fixed transform of these worlds (`namespaces`, the world indices `worlds`), each
    world's root hung from the fleet frame."""
    msg = TFMessage()
    identity = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    for ns, fixed in zip(namespaces, spec.static_of(worlds), strict=True):
        if frame(ns, spec.root) != spec.fleet_frame:  # a root-namespace world's `world` body is the fleet frame
            msg.transforms.append(_transform(spec.fleet_frame, frame(ns, spec.root), identity))
        for parent, child, value in fixed:
            msg.transforms.append(_transform(frame(ns, parent), frame(ns, child), value))
    for t in msg.transforms:
        t.header.stamp.sec, t.header.stamp.nanosec = sec, nanosec
    return msg


class TfPublishers:
    """tf, tf_static and robot_description of worlds [lo, lo + len(namespaces)) named `namespaces`."""

    def __init__(self, node: Node, spec: TfSpec, namespaces: list[str], lo: int = 0, *, all_topics: bool = False):
        self.node = node
        self.spec = spec
        self.namespaces = namespaces
        self.lo = lo
        self.channel = spec.channel
        self.fleet = TfTemplate(spec, namespaces) if spec.all_moving else None
        self._fleet_pub = node.create_publisher(TFMessage, "/tf", DYNAMIC_QOS)
        self._fleet_static = node.create_publisher(TFMessage, "/tf_static", STATIC_QOS)
        self._fleet_static.publish(static_message(spec, namespaces, range(lo, lo + len(namespaces))))
        self._world: list[Any] = [None] * len(namespaces)  # per world: (template, publisher)
        self._wanted: list[int] = []  # worlds with a /<ns>/tf subscriber
        self._fleet_wanted = False
        # per-world topics, created once somebody subscribes: topic -> (kind, row)
        self._on_request: dict[str, tuple[str, int]] = {}
        for row, ns in enumerate(namespaces):
            # a root-namespace world's /tf and /tf_static are the fleet's own
            kinds = ("robot_description", "mujoco_robot_description")
            for kind in ("tf", "tf_static", *kinds) if ns else kinds:
                if topic_name(ns, kind) != spec.source_topic:  # its own publisher keeps the topic we read
                    self._on_request[topic_name(ns, kind)] = (kind, row)
            for prefix, _ in spec.robot_descriptions:  # each robot's of a world of several
                self._on_request[topic_name(ns, f"{prefix}robot_description")] = (prefix, row)
        self._keep: list[Any] = []  # publishers of latched messages
        # a world in the root namespace stands in for a ros2_control robot: /robot_description is
        # published at once by a node named as the one that publishes it there, robot_state_publisher
        # (no parameter services: it is never spun), unless another node already does (the topic
        # the description was read from)
        self.rsp: Node | None = None
        if "" in namespaces and "/robot_description" in self._on_request:
            self.rsp = Node(RSP, context=node.context, start_parameter_services=False)
            self._create("/robot_description", self.rsp)
        if all_topics:
            for topic in list(self._on_request):
                self._create(topic)

    @property
    def wanted(self) -> bool:
        """Whether anybody listens to a moving transform of these worlds."""
        return self._fleet_wanted or bool(self._wanted)

    def requested(self, topic: str) -> bool:
        """The graph scan saw `topic`: create its publisher if somebody subscribes. True if ours."""
        if topic not in self._on_request:
            return False
        if self.node.count_subscribers(topic) > 0:
            self._create(topic)
        return True

    def close(self) -> None:
        if self.rsp is not None:
            self.rsp.destroy_node()
            self.rsp = None

    def _create(self, topic: str, owner: Node | None = None) -> None:
        """`topic`'s publisher, on `owner` (default: the worker's node), and its latched message."""
        kind, row = self._on_request.pop(topic)
        ns = self.namespaces[row]
        if kind == "tf":
            if self.spec.all_moving:
                self._world[row] = (TfTemplate(self.spec, [ns]), self.node.create_publisher(TFMessage, topic, DYNAMIC_QOS))
        elif kind == "tf_static":
            pub = self.node.create_publisher(TFMessage, topic, STATIC_QOS)
            pub.publish(static_message(self.spec, [ns], [self.lo + row]))
            self._keep.append(pub)
        else:
            pub = (owner or self.node).create_publisher(String, topic, STATIC_QOS)
            text = dict(self.spec.robot_descriptions).get(kind)  # a robot's, keyed by its prefix
            if text is None:
                text = self.spec.description if kind == "robot_description" else self.spec.mjcf
            pub.publish(String(data=text))
            self._keep.append(pub)

    def refresh(self) -> None:
        """Re-read who listens (lazy publishing)."""
        self._fleet_wanted = self.fleet is not None and self._fleet_pub.get_subscription_count() > 0
        self._wanted = [r for r, w in enumerate(self._world) if w is not None and w[1].get_subscription_count() > 0]

    def publish(self, poses: np.ndarray, sec: int, nanosec: int) -> int:
        """poses: this worker's rows of the tf channel (TfSpec.channel). Returns the messages published."""
        n = 0
        if self._fleet_wanted:  # every world's transforms; else those of the worlds listened to
            values = self.spec.moving_transforms(poses)
            self._fleet_pub.publish(self.fleet.fill(values, sec, nanosec))
            n += 1
            per_world = values[self._wanted]
        else:
            per_world = self.spec.moving_transforms(poses[self._wanted])
        for k, r in enumerate(self._wanted):
            template, pub = self._world[r]
            pub.publish(template.fill(per_world[k : k + 1], sec, nanosec))
            n += 1
        return n
