"""The workers' liveness: each worker's tick counter (`beat`, its writer `Beat`), which the
supervisor watches (`beat`), and since when a worker has stopped ticking (`worker.hung`,
written by the supervisor, `mark_hung`), which every worker's /diagnostics reports (`hung`).
And the physics process's: when it last ran a period, idled or waited (`physics.alive`,
`physics_alive`, written by the supervisor each time the loop looks at it), which worker 0
watches (`PhysicsWatch`): a stopped physics process (SIGSTOP, a debugger) is said, not only
seen as topics gone quiet. No rclpy here.
"""

from __future__ import annotations

import numpy as np

from batchsim.memory import Memory


def liveness_arrays(nworker: int) -> list[tuple[str, tuple[int, ...], str]]:
    return [
        ("beat", (nworker,), "i8"),  # per worker: ticks served
        ("worker.hung", (nworker,), "f8"),  # per worker: since when (epoch s) it has not ticked; 0: it does
        ("physics.alive", (1,), "f8"),  # when (epoch s) the loop last looked at the bridge; 0: not yet
    ]


class Beat:
    """Worker `worker`'s side: one tick served."""

    def __init__(self, memory: Memory, worker: int):
        self._beat = memory["beat"]
        self.worker = worker

    def tick(self) -> None:
        self._beat[self.worker] += 1


def beat(memory: Memory, worker: int) -> int:
    """The supervisor: `worker`'s ticks so far."""
    return int(memory["beat"][worker])


def mark_hung(memory: Memory, worker: int, since: float) -> None:
    """The supervisor: `worker` has not ticked since `since` (epoch s); 0: it ticks again."""
    memory["worker.hung"][worker] = since


def hung(memory: Memory) -> np.ndarray:
    """A worker's /diagnostics: (nworker,) since when (epoch s) each worker has not ticked, 0 where it does."""
    return memory["worker.hung"]


PHYSICS_STALL = 3.0  # s without a look from the loop before the physics process is said to have stopped


def physics_alive(memory: Memory, now: float) -> None:
    """The physics process (the supervisor, each period, while idle or waiting): it runs."""
    memory["physics.alive"][0] = now


class PhysicsWatch:
    """A worker's watch on the physics process: `check(now)` gives a line to log when it stops
    (nothing from it for PHYSICS_STALL s) and when it runs again; `stalled` meanwhile."""

    def __init__(self, memory: Memory):
        self._alive = memory["physics.alive"]
        self.stalled = 0.0  # since when (epoch s), 0: it runs

    def check(self, now: float) -> str | None:
        last = float(self._alive[0])
        if not last:
            return None  # the loop has not looked yet (its first period may be compiling)
        if not self.stalled and now - last > PHYSICS_STALL:
            self.stalled = last
            return (
                f"the physics process has not finished a period for {now - last:.1f} s (one this long, or the process "
                "stopped: a debugger, SIGSTOP, a machine out of memory): every world's topics hold their last state"
            )
        if self.stalled and now - last <= PHYSICS_STALL:
            gone, self.stalled = now - self.stalled, 0.0
            return f"the physics process runs again, after {gone:.1f} s"
        return None

