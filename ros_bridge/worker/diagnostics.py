"""A worker's bookkeeping of rejected commands, and its worlds' /diagnostics.

Every rejection is written to shared memory (count, period and last reason per world, for
the physics process's status line) and counted per world, topic and reason here; the
controllers' own rejections in the loop arrive through the `hrej` block. /diagnostics
(diagnostic_msgs/DiagnosticArray) carries one status per world: its robots (a fleet file's world), its status bits, whether
it is frozen or its commands timed out, its rejection counts, and the messages published per
state topic (`published joint_states`: how many went out, counted where they are published,
for benchmarks/fleet.py to set against what subscribers received) and those due but missed
(`missed joint_states`: the worker read their snapshots too late; `missed <camera or lidar
topic>`: samples overwritten in their block before the worker took them); and one ERROR status per
other bridge worker that has stopped answering (the supervisor's `worker.hung`), naming
the worlds nobody serves meanwhile.
"""

from __future__ import annotations

import threading
import time as wallclock
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import QoSProfile

from batchsim.memory import Memory
from batchsim.stamps import stamp_of
from ros_bridge import world_status
from ros_bridge.protocol.commands import Problem, RejectionWriter, bad_commands
from ros_bridge.protocol.liveness import PhysicsWatch, hung
from ros_bridge.protocol.world_params import read_line


class Diagnostics:
    """Rejections and /diagnostics for worlds [lo, hi) named `namespaces`."""

    def __init__(
        self,
        node: Node,
        memory: Memory,
        lo: int,
        hi: int,
        namespaces: list[str],
        workers: list[str] | None = None,
        robots: tuple[str, ...] = (),
    ):
        """`workers`: every worker's worlds, as the log names them (`/world_0 .. /world_63`);
        `robots`: the robots of each world of a fleet file (batchsim.fleet), named in its status."""
        self.lo, self.hi = lo, hi
        self._robots = [KeyValue(key="robots", value=", ".join(robots))] if robots else []
        self.workers = workers or []
        self.hung = hung(memory)
        self.physics: PhysicsWatch | None = None  # worker 0's watch on the physics process
        self.memory = memory
        self.randomized = "wp.text" in memory  # each world's draw (ros_bridge/protocol/world_params.py)
        self.namespaces = namespaces
        self.rejections = RejectionWriter(memory, "rej")
        self.host_rejections = RejectionWriter(memory, "hrej")
        # per world (row): rejections per (topic, reason)
        self._rejected: list[dict[tuple[str, str], int]] = [{} for _ in namespaces]
        self._lock = threading.Lock()
        self._host_seen = self.host_rejections.count[lo:hi].copy()
        self._heads: dict[tuple[int, int], list[KeyValue]] = {}  # _head's, per (status bits, flags)
        # per state topic (joint_states, ...): messages published per world (row), since start
        self._published: dict[str, np.ndarray] = {}
        self._missed: dict[str, np.ndarray] = {}  # ... and not published, due but its snapshot gone
        self._pub = node.create_publisher(DiagnosticArray, "/diagnostics", QoSProfile(depth=10))

    def reject(self, world: int, period: int, topic: str, problem: Problem, reason: str) -> None:
        """One command for `world` on `topic` was refused."""
        self.rejections.put(world, period, topic, reason)
        self.count(world - self.lo, topic, problem, 1)

    def dropped(self, world: int, period: int, topic: str, count: int, reason: str) -> None:
        """`count` messages for `world` on `topic` were dropped unread (a flood)."""
        self.rejections.put(world, period, topic, reason, count)
        self.count(world - self.lo, topic, Problem.FLOOD, count)

    def count(self, row: int, topic: str, problem: Problem, count: int) -> None:
        with self._lock:
            counts = self._rejected[row]
            counts[topic, problem.value] = counts.get((topic, problem.value), 0) + count

    def published(self, topic: str, rows: list[int], missed: int = 0) -> None:
        """One message on `topic` went out to each of `rows` (the worker's publishing thread),
        after `missed` periods it was due in and could not be published (its snapshots gone)."""
        self._add(self._published, topic, rows, 1)
        if missed:
            self._add(self._missed, topic, rows, missed)

    def missed(self, topic: str, rows: np.ndarray, counts: np.ndarray) -> None:
        """Samples on `topic` that `rows` never got (a camera's or lidar's, overwritten in its
        block before the worker looked), `counts` (n,) of them per row."""
        self._add(self._missed, topic, rows, counts)

    def _add(self, counter: dict[str, np.ndarray], topic: str, rows: Any, n: Any) -> None:
        """counter[topic][rows] += n, the per-world counts made on first use."""
        counts = counter.get(topic)
        if counts is None:
            counts = counter[topic] = np.zeros(len(self.namespaces), dtype=np.int64)
        counts[rows] += n

    def _head(self, bits: int, flags: int) -> list[KeyValue]:
        """The key values a world's status starts with, made once per (bits, flags) and shared
        by the worlds in that state (a message's fields are serialized by value)."""
        head = self._heads.get((bits, flags))
        if head is None:
            head = self._heads[(bits, flags)] = [KeyValue(key=k, value=v) for k, v in world_status.values(bits, flags)]
        return head

    def publish(self, snap) -> None:
        """One DiagnosticArray for this worker's worlds, from snapshot `snap`, if someone listens."""
        if self._pub.get_subscription_count() == 0:
            return
        out = DiagnosticArray()
        sec, nanosec = stamp_of(snap.time)
        out.header.stamp.sec, out.header.stamp.nanosec = sec, nanosec
        mine, host = self.rejections, self.host_rejections
        # what the controllers refused in the loop since the last round, on its last topic
        host_counts = host.count[self.lo : self.hi].copy()
        for row in np.flatnonzero(host_counts != self._host_seen).tolist():
            self.count(row, host.topic(self.lo + row), Problem.INVALID, int(host_counts[row] - self._host_seen[row]))
        self._host_seen = host_counts
        with self._lock:
            rejected = [sorted(c.items()) for c in self._rejected]
        published = [(f"published {topic}", counts.tolist()) for topic, counts in sorted(self._published.items())]
        missed = [(f"missed {topic}", counts.tolist()) for topic, counts in sorted(self._missed.items())]
        for row, ns in enumerate(self.namespaces):
            w = self.lo + row
            bits = int(snap.status[row])
            flags = int(snap.flags[row])
            count, last = bad_commands(mine, host, w)
            out.status.append(
                DiagnosticStatus(
                    level=bytes([world_status.level(bits, flags)]),  # a ROS byte field
                    name=world_status.status_name(ns),
                    message=world_status.message(bits, flags, last),
                    hardware_id=ns,
                    values=self._head(bits, flags)
                    + [
                        KeyValue(key="bad_commands", value=str(count)),
                        KeyValue(key="last_problem", value=last),
                    ]
                    + [KeyValue(key=f"rejected {topic} {reason}", value=str(n)) for (topic, reason), n in rejected[row]]
                    + [KeyValue(key=key, value=str(counts[row])) for key, counts in published]
                    + [KeyValue(key=key, value=str(counts[row])) for key, counts in missed if counts[row]]
                    + ([KeyValue(key="randomized", value=read_line(self.memory, w))] if self.randomized else [])
                    + self._robots,
                )
            )
        now = wallclock.time()
        if self.physics is not None and self.physics.stalled:
            out.status.append(
                DiagnosticStatus(
                    level=DiagnosticStatus.ERROR,
                    name="batchsim: simulation",
                    message=f"the physics process has not run a period for {now - self.physics.stalled:.1f} s",
                    hardware_id="batchsim",
                )
            )
        for j, since in enumerate(self.hung.tolist()):
            if since and j < len(self.workers):
                out.status.append(
                    DiagnosticStatus(
                        level=DiagnosticStatus.ERROR,
                        name=f"batchsim: bridge worker {j}",
                        message=f"not answering for {now - since:.1f} s: {self.workers[j]} are not served",
                        hardware_id=f"bridge_worker_{j}",
                        values=[KeyValue(key="worlds", value=self.workers[j])],
                    )
                )
        self._pub.publish(out)

