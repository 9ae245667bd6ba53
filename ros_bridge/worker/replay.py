"""`batchsim replay FILE`: republish an MCAP recording over ROS 2, as `ros2 bag play` would.

Every channel becomes a publisher of its schema's type on its topic, with the QoS the
recording says it was offered (latched topics, /tf_static and robot_description, stay
transient local); messages go out as their recorded CDR bytes, paced by their log times
(sim time) times `rate`. /clock is republished as recorded; a recording without it gets one
from the log times (at most CLOCK_RATE Hz), so `use_sim_time` nodes follow the replay.
A batchsim recording names its worlds (its `batchsim` metadata): `worlds` picks some, and
the fleet-wide topics (/clock, /tf, /tf_static) go out whole; /diagnostics goes out with the
picked worlds' statuses only (a message with none of them is not sent).

The file is read as a stream, record by record, so a recording that was cut short (the
recorder was killed) replays up to its last complete chunk, after one line that says so.
"""

from __future__ import annotations

import json
import re
import time as wallclock
from collections.abc import Callable, Sequence
from typing import Any, BinaryIO

import rclpy
from mcap.records import Channel, DataEnd, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rosgraph_msgs.msg import Clock

from ros_bridge.recording_file import ReplayError, check_file, cut_short_errors
from ros_bridge.worker.messages import clock_payload, message_type

CLOCK_RATE = 100.0  # Hz of the /clock made up for a recording without one
DRAIN_TIMEOUT = 5.0  # s the replay waits at its end for subscribers to acknowledge the last messages
FLEET = ("/clock", "/tf", "/tf_static")
DIAGNOSTICS = "/diagnostics"  # one status per world (hardware_id: its namespace): filtered by --worlds


def _qos(channel: Channel) -> QoSProfile:
    """The QoS rosbag2's offered_qos_profiles names (durability, reliability, depth), else reliable depth 10."""
    text = channel.metadata.get("offered_qos_profiles", "")

    def number(key: str, default: int) -> int:
        match = re.search(rf"^\s*-?\s*{key}:\s*(\w+)", text, flags=re.MULTILINE)
        if match is None:
            return default
        value = match.group(1)
        names = {"transient_local": 1, "volatile": 2, "reliable": 1, "best_effort": 2, "keep_last": 1}
        return int(value) if value.isdigit() else names.get(value, default)

    return QoSProfile(
        depth=max(1, number("depth", 10)),
        history=HistoryPolicy.KEEP_LAST,
        reliability=ReliabilityPolicy.BEST_EFFORT
        if number("reliability", 1) == 2
        else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL
        if number("durability", 2) == 1
        else DurabilityPolicy.VOLATILE,
    )


class Replay:
    """Republishes one recording. Args: path; worlds (world numbers, None: all); rate (1: real
    time); delay (wall seconds between the first publishers and the first message, for discovery);
    say (where its lines go)."""

    def __init__(
        self, path: str, worlds: Sequence[int] | None, rate: float, delay: float, say: Callable[[str], None]
    ):
        if not rate > 0:
            raise ReplayError(f"--rate must be > 0, got {rate:g}")
        self.path, self.worlds, self.rate, self.delay, self.say = path, worlds, rate, delay, say
        self.complete = check_file(path)
        self.prefixes: tuple[str, ...] | None = None  # the picked worlds' topic prefixes
        self.published = 0
        self.first = self.last = None
        self._schemas: dict[int, Schema] = {}
        self._publishers: dict[int, Any] = {}  # channel id -> publisher, or None: not replayed
        self._diagnostics: set[int] = set()  # the /diagnostics channels, filtered to the picked worlds
        self._clock: Any = None
        self._clock_recorded = False
        self._last_clock = -1
        self.stopped = False

    def run(self, node: Node) -> int:
        """Publish every message; the number published."""
        if not self.complete:
            self.say(f"warning: {self.path} was cut short (it has no summary: was the recorder killed?); "
                     "replaying its complete chunks")  # fmt: skip
        with open(self.path, "rb") as f:
            self._play(node, f)
        self._drain()
        if self.worlds is not None and self.prefixes is None:
            raise ReplayError(
                f"{self.path} names no worlds (it is not a batchsim recording): replay it without --worlds"
            )
        return self.published

    def _drain(self, timeout: float = DRAIN_TIMEOUT) -> None:
        """Wait until the subscribers acknowledged what the reliable publishers sent: the last
        messages were lost when the process exited right after publishing them."""
        deadline = wallclock.monotonic() + timeout
        for pub in [p for p in (*self._publishers.values(), self._clock) if p is not None]:
            left = deadline - wallclock.monotonic()
            if left <= 0 or not pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
                self.say(f"warning: not every subscriber acknowledged the last messages within {timeout:g} s")
                return

    def _play(self, node: Node, f: BinaryIO) -> None:
        start: float | None = None
        try:
            for record in StreamReader(f, skip_magic=False).records:
                if self.stopped:
                    return
                if isinstance(record, Message):
                    pub = self._publishers.get(record.channel_id)
                    if pub is None:
                        continue
                    if start is None:
                        wallclock.sleep(self.delay)
                        start, self.first = wallclock.monotonic(), record.log_time
                    due = start + (record.log_time - self.first) * 1e-9 / self.rate
                    wait = due - wallclock.monotonic()
                    if wait > 0:
                        wallclock.sleep(wait)
                    if not self._clock_recorded and record.log_time - self._last_clock >= 1e9 / CLOCK_RATE:
                        self._last_clock = record.log_time
                        self._clock.publish(clock_payload(*divmod(record.log_time, 1_000_000_000)))
                    if record.channel_id in self._diagnostics:
                        kept = self._picked_statuses(record.data)
                        if kept is None:
                            continue
                        pub.publish(kept)
                    else:
                        pub.publish(record.data)
                    self.published += 1
                    self.last = record.log_time
                elif isinstance(record, Schema):
                    self._schemas[record.id] = record
                elif isinstance(record, Channel):
                    if record.id not in self._publishers:
                        self._publishers[record.id] = self._publisher(node, record)
                elif isinstance(record, Metadata) and record.name == "batchsim":
                    self._pick(record)
                elif isinstance(record, DataEnd):
                    return
        except ReplayError:
            raise
        except cut_short_errors() as e:
            if self.complete:
                raise ReplayError(
                    f"{self.path}: unreadable after {self.published} messages ({type(e).__name__}: {e})"
                ) from None
            if not self.published:
                raise ReplayError(
                    f"{self.path} was cut short before its first complete chunk: nothing to replay"
                ) from None

    def _pick(self, record: Metadata) -> None:
        namespaces = json.loads(record.metadata.get("namespaces", "[]"))
        numbers = json.loads(record.metadata.get("worlds", "[]"))
        if self.worlds is None:
            return
        missing = [w for w in self.worlds if w not in numbers]
        if missing:
            held = (
                f"{numbers[0]}..{numbers[-1]}"
                if numbers == list(range(numbers[0], numbers[-1] + 1))
                else str(numbers)
            )
            raise ReplayError(
                f"--worlds names world {missing[0]}, which {self.path} does not hold (worlds {held})"
            )
        self.prefixes = tuple(f"/{namespaces[numbers.index(w)]}/" for w in self.worlds)

    def _publisher(self, node: Node, channel: Channel) -> Any:
        topic = channel.topic
        if topic == "/clock":
            self._clock_recorded = True
            return self._clock  # one publisher on /clock
        if self.worlds is not None and topic == DIAGNOSTICS:
            self._diagnostics.add(channel.id)
        elif self.worlds is not None and topic not in FLEET:
            if self.prefixes is None or not topic.startswith(self.prefixes):
                return None
        schema = self._schemas.get(channel.schema_id)
        if schema is None or channel.message_encoding != "cdr":
            self.say(f"warning: {topic}: not a ROS 2 CDR channel; not replayed")
            return None
        try:
            cls = message_type(schema.name)
        except (ImportError, AttributeError, ValueError):
            self.say(f"warning: {topic}: no message type {schema.name} installed; not replayed")
            return None
        return node.create_publisher(cls, topic, _qos(channel))

    def _picked_statuses(self, data: bytes) -> Any:
        """A recorded DiagnosticArray with the picked worlds' statuses only, or None if it has none."""
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.serialization import deserialize_message

        msg = deserialize_message(data, DiagnosticArray)
        names = {p.strip("/") for p in self.prefixes or ()}
        msg.status = [s for s in msg.status if s.hardware_id in names]
        return msg if msg.status else None

    def clock_publisher(self, node: Node) -> None:
        self._clock = node.create_publisher(Clock, "/clock", QoSProfile(depth=1))


def replay(path: str, worlds: Sequence[int] | None = None, rate: float = 1.0, delay: float = 1.0,
           say: Callable[[str], None] = print) -> tuple[int, float, float]:  # fmt: skip
    """Replay `path` over ROS 2 (its own context and node, `batchsim_replay`): (messages
    published, first and last sim time in s). ReplayError: one line naming the problem."""
    player = Replay(path, worlds, rate, delay, say)
    context = Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = Node("batchsim_replay", context=context)
        player.clock_publisher(node)
        try:
            n = player.run(node)
        except KeyboardInterrupt:
            n = player.published
        first = (player.first or 0) * 1e-9
        last = (player.last or 0) * 1e-9
        node.destroy_node()
        return n, first, last
    finally:
        rclpy.try_shutdown(context=context)
