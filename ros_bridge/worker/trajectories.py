"""Trajectories a worker takes, from the controllers' topics and from action goals, handed
to the loop in batches: one ring record per controller input and flush, however many
messages arrived (a thousand goals sent at once are one batch)."""

from __future__ import annotations

import threading
import time as wallclock
from collections.abc import Callable
from typing import Any

import numpy as np

from batchsim.controllers.topics import trajectory_batch
from batchsim.memory import Memory, Ring
from ros_bridge.naming import topic_name
from ros_bridge.plan import FleetPlan
from ros_bridge.protocol.commands import Problem
from ros_bridge.protocol.requests import Kind, encode_trajectories

FLUSH_AFTER = 0.001  # s: trajectories reach the loop this long after they arrive, at most


class TrajectoryIntake:
    """Pending trajectories per input, flushed to the worker's ring.

    Args:
      reject: `reject(world, topic, problem, reason)`, the worker's rejection.
      nudge: tells the loop something arrived (lockstep).
    """

    def __init__(
        self,
        plan: FleetPlan,
        memory: Memory,
        ring: Ring,
        ring_lock: threading.Lock,
        reject: Callable[[int, str, Problem, str], None],
        nudge: Callable[[], None],
    ):
        self.plan = plan
        self.memory = memory
        self.ring = ring
        self._ring_lock = ring_lock
        self._reject = reject
        self._nudge = nudge
        self._pending: dict[int, list] = {}  # input -> [(world, parsed...)]
        self._pending_goals: dict[int, dict[int, tuple]] = {}  # input -> {message index: goal}
        self._pending_since = 0.0
        self._pending_lock = threading.Lock()

    @property
    def pending(self) -> bool:
        return bool(self._pending)

    def due(self) -> bool:
        """Trajectories have waited FLUSH_AFTER: time to flush."""
        return bool(self._pending) and wallclock.monotonic() - self._pending_since >= FLUSH_AFTER

    def submit(self, i: int, w: int, parsed: tuple, goal: tuple | None = None) -> None:
        """A trajectory for input `i` in world `w`, handed to the loop with the next flush;
        `goal`: (tag, path tolerance, goal tolerance, goal time tolerance) of an action goal."""
        with self._pending_lock:
            if not self._pending:
                self._pending_since = wallclock.monotonic()
            messages = self._pending.setdefault(i, [])
            if goal is not None:
                self._pending_goals.setdefault(i, {})[len(messages)] = goal
            messages.append((w, *parsed))

    def flush(self) -> None:
        """Hand every trajectory that arrived to the loop: one ring record per input."""
        with self._pending_lock:
            pending, self._pending = self._pending, {}
            goals, self._pending_goals = self._pending_goals, {}
        for i, messages in pending.items():
            spec = self.plan.inputs[i]
            batch, kept, rejected = trajectory_batch(spec.joints, messages, **_goal_arrays(goals.get(i), len(messages), len(spec.joints)))
            for k, reason in rejected:
                w = messages[k][0]
                self._reject(w, topic_name(self.plan.namespaces[w], spec.topic), Problem.MALFORMED, reason)
            if not len(batch):
                continue
            with self._ring_lock:
                ok = self.ring.put(Kind.TRAJECTORY, encode_trajectories(i, batch))
            if not ok:
                for w in batch.worlds.tolist():
                    self._reject(
                        w, topic_name(self.plan.namespaces[w], spec.topic), Problem.BACKLOG, "the loop is too far behind to take it"
                    )
                continue
            np.add.at(self.memory[f"{spec.slots}.seq"], batch.worlds, 1)
        self._nudge()


def _goal_arrays(goals: dict[int, tuple] | None, n: int, njoint: int) -> dict[str, Any]:
    """trajectory_batch's goal arguments for `n` messages, the `goals` among them
    ({message index: (tag, path (njoint, 3), goal (njoint, 3), goal time tolerance)})."""
    if not goals:
        return {}
    tags, path, final, goal_time = np.zeros(n, np.int64), np.zeros((n, njoint, 3)), np.zeros((n, njoint, 3)), np.zeros(n)
    for k, (tag, p, g, t) in goals.items():
        tags[k], path[k], final[k], goal_time[k] = tag, p, g, t
    return {"goals": tags, "path_tolerance": path, "goal_tolerance": final, "goal_time_tolerance": goal_time}
