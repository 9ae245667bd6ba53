"""Bounded intake: a flood on one world's input topic costs that world, never its neighbours.

Every message a worker's subscription takes costs its executor thread (and the GIL, which
the thread publishing every world's state needs) before any callback can look at it: 50,000
trajectories in 5 s to one world of 16 on one worker took the other 15 from 100 to 66-90
joint_states/s with gaps of up to 0.7 s, even with a callback that returned at once; without
a reader for the flooded topic, the same flood cost them nothing (benchmarks/flood.py). So
each input subscription (one world's topic) takes at most `limit` messages per WINDOW of
wall time, FLOOR plus PER_PERIOD per control period the loop advanced in the window before
and in this one so far, up to CAP (a lockstep commander flat out sends one per period, and
passes); the rest of the window's messages are dropped unread, and a topic that went over
is not listened to for PAUSE s, twice as long each time it goes over again at once (up to 8
PAUSE): its subscription is destroyed (DDS then drops the flood before the worker sees it)
and created again after. Each time it comes back costs the worker a burst (the flood's
first window), so a flood that goes on is heard less and less often. The dropped messages are counted per world in
/diagnostics (`rejected <topic> flood`), and one log line per topic every 2 s says so.

Runs on the executor thread: `service()` after every spin, the callbacks during it.
"""

from __future__ import annotations

import time as wallclock
from collections.abc import Callable
from typing import Any

from ros_bridge.protocol.commands import Problem

WINDOW = 0.1  # s of wall time
FLOOR = 20  # messages per topic and window, whatever the loop does (paused: only these)
PER_PERIOD = 4  # more messages per topic and window, per control period advanced
CAP = 1000  # messages per topic and window at most (--rtf 0 runs thousands of periods a second)
PAUSE = 1.0  # s not listening to a topic that went over


class Intake:
    """The worker's input subscriptions, each bounded.

    Args:
      node: creates and destroys the subscriptions.
      qos: their QoS.
      period: the loop's current control period (the worker's newest snapshot).
      diagnostics: counts what was dropped (ros_bridge/worker/diagnostics.py).
      throttle: the worker's rate-limited log (ros_bridge/throttle.py).
      clock: monotonic seconds (tests pass a fake).
    """

    def __init__(
        self,
        node: Any,
        qos: Any,
        period: Callable[[], int],
        diagnostics: Any,
        throttle: Any,
        clock: Callable[[], float] = wallclock.monotonic,
    ):
        self.node = node
        self.qos = qos
        self.period = period
        self.diagnostics = diagnostics
        self.throttle = throttle
        self.clock = clock
        self.limit = FLOOR
        self._entries: list[tuple[int, type, str, Callable[[Any], None]]] = []  # world, type, topic, callback
        self._subs: list[Any] = []  # None while paused
        self._counts: list[int] = []  # messages this window, per subscription
        self._paused: dict[int, float] = {}  # subscription -> when it listens again
        self._over: list[int] = []  # subscriptions over their limit, not paused yet
        self._strikes: dict[int, int] = {}  # subscription -> pauses in a row
        self._calm: dict[int, float] = {}  # subscription -> when its strikes are forgotten
        self._next = 0.0
        self._last_period: int | None = None  # the period when this window began
        self._before = 0  # periods the loop advanced in the window before

    def subscribe(self, world: int, msg_type: type, topic: str, callback: Callable[[Any], None]) -> None:
        k = len(self._entries)
        self._entries.append((world, msg_type, topic, self._bounded(k, callback)))
        self._counts.append(0)
        self._subs.append(None)
        self._create(k)

    def _bounded(self, k: int, callback: Callable[[Any], None]) -> Callable[[Any], None]:
        counts = self._counts

        def bounded(msg: Any) -> None:
            n = counts[k] = counts[k] + 1
            if n <= self.limit or n <= self._grown():
                callback(msg)
            elif k not in self._paused:
                self._over.append(k)  # paused at once, by service()

        return bounded

    def _grown(self) -> int:
        """The window's limit with the periods advanced in it so far (a lockstep commander
        that starts flat out after a quiet window is not cut off)."""
        if self._last_period is not None:
            self.limit = max(self.limit, min(CAP, FLOOR + PER_PERIOD * (self._before + self.period() - self._last_period)))
        return self.limit

    def _create(self, k: int) -> None:
        _world, msg_type, topic, callback = self._entries[k]
        self._subs[k] = self.node.create_subscription(msg_type, topic, callback, self.qos)

    def service(self) -> None:
        """The executor thread, between spins: pause the topics that went over their limit (at
        once), and at each window's end count what they dropped, listen again to those paused
        long enough, and set the next window's limit."""
        now = self.clock()
        while self._over:
            k = self._over.pop()
            if k in self._paused:
                continue
            if self._subs[k] is not None:
                self.node.destroy_subscription(self._subs[k])
                self._subs[k] = None
            self._strikes[k] = strikes = self._strikes.get(k, 0) + 1
            self._paused[k] = now + PAUSE * 2 ** min(strikes - 1, 3)  # 1, 2, 4, 8 s while it goes on
        if now < self._next:
            return
        self._next = now + WINDOW
        counts, limit = self._counts, self.limit
        for k, n in enumerate(counts):
            if n > limit:
                world, _type, topic, _cb = self._entries[k]
                self._dropped(world, topic, n - limit)
            if n:
                counts[k] = 0
        for k, until in list(self._paused.items()):
            if now >= until:
                del self._paused[k]
                self._create(k)
                self._calm[k] = now + PAUSE  # within its limit this long after: its strikes are forgotten
        for k, until in list(self._calm.items()):
            if k in self._paused:
                del self._calm[k]
            elif now >= until:
                del self._calm[k]
                self._strikes.pop(k, None)
        period = self.period()
        self._before = 0 if self._last_period is None else max(0, period - self._last_period)
        self._last_period = period
        self.limit = min(CAP, FLOOR + PER_PERIOD * self._before)

    def _dropped(self, world: int, topic: str, count: int) -> None:
        reason = f"more than {self.limit} messages in {WINDOW:g} s: not listening for {PAUSE:g} s"
        self.diagnostics.dropped(world, self.period(), topic, count, reason)
        self.throttle.warn((topic, Problem.FLOOD), f"dropped {count} messages on {topic}: {reason}")

    @property
    def paused(self) -> list[str]:
        """Topics not listened to now."""
        return [self._entries[k][2] for k in self._paused]
