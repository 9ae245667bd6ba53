"""A client built from another definition of a type batchsim builds: said, not garbled.

batchsim builds tf2_msgs, control_msgs, controller_manager_msgs and
mujoco_ros2_control_msgs itself (ros_bridge/interfaces/). Fast DDS matches endpoints by
the type's name alone, so a node built from another release's definition of, say,
JointTrajectoryControllerState connects and then receives messages it decodes wrong or
not at all. Every endpoint carries its type's RIHS01 hash in the graph, though: at each
graph scan (every second) the worker looks at up to PER_SCAN of its own topics of those
packages (its worlds' and the fleet's /tf, in turn), each one whose endpoint count changed,
and a remote endpoint whose hash differs from this node's own for the same type gets one
error line naming the topic, the node, the type and both hashes. Only its own topics, and
a bounded number per scan: with thousands of action servers in the graph, counting every
topic's endpoints each second kept an H100 host's workers from publishing at all. Services (controller_manager's) carry no hash that rclpy shows; their types'
definitions are the ones `tests/test_interfaces.py` checks against upstream.
"""

from __future__ import annotations

from rclpy.node import Node

#: the packages whose types batchsim builds itself
CHECKED = ("tf2_msgs/", "control_msgs/", "controller_manager_msgs/", "mujoco_ros2_control_msgs/")
PER_SCAN = 32  # topics looked at per graph scan


class TypeCheck:
    """Checks the endpoints of `node`'s topics of CHECKED packages against its own."""

    def __init__(self, node: Node, prefixes: tuple[str, ...] = ("/",)):
        """`prefixes`: the beginnings of this worker's topic names (`/world_3/`, ..., `/tf`)."""
        self.node = node
        self.prefixes = prefixes
        self._cursor = 0
        self.logger = node.get_logger()
        self._counts: dict[str, int] = {}  # topic -> endpoints when last looked at
        self._seen: set[bytes] = set()  # remote endpoints looked at
        self.mismatches: list[str] = []  # one line per mismatched remote endpoint

    def scan(self, topics: list[tuple[str, list[str]]]) -> None:
        """`topics`: the graph's (name, types), as Node.get_topic_names_and_types gives them."""
        node = self.node
        mine = [name for name, types in topics if name.startswith(self.prefixes) and any(t.startswith(CHECKED) for t in types)]
        if not mine:
            return
        start = self._cursor % len(mine)
        turn = (mine[start:] + mine[:start])[:PER_SCAN]
        self._cursor = start + len(turn)
        for name in turn:
            count = node.count_publishers(name) + node.count_subscribers(name)
            if self._counts.get(name) == count:
                continue
            self._counts[name] = count
            self._check(name)

    def _check(self, topic: str) -> None:
        node = self.node
        infos = node.get_publishers_info_by_topic(topic) + node.get_subscriptions_info_by_topic(topic)
        mine = node.get_name(), node.get_namespace()
        ours = {i.topic_type: i.topic_type_hash for i in infos if (i.node_name, i.node_namespace) == mine}
        for info in infos:
            gid = bytes(info.endpoint_gid)
            if gid in self._seen or (info.node_name, info.node_namespace) == mine:
                continue
            self._seen.add(gid)
            own = ours.get(info.topic_type)
            if own is None or info.topic_type_hash == own:
                continue
            line = (
                f"{topic}: node {info.node_namespace.rstrip('/')}/{info.node_name} was built with another "
                f"definition of {info.topic_type} (type hash {info.topic_type_hash}, batchsim's {own}): its "
                "messages will not be understood; build both from the same definitions (batchsim's are "
                "upstream Jazzy's, ros_bridge/interfaces/definitions)"
            )
            self.mismatches.append(line)
            self.logger.error(line)
