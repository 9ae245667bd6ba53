"""The workers' liveness: each worker's tick counter (`beat`, its writer `Beat`), which the
supervisor watches (`beat`), and since when a worker has stopped ticking (`worker.hung`,
written by the supervisor, `mark_hung`), which every worker's /diagnostics reports (`hung`).
No rclpy here.
"""

from __future__ import annotations

import numpy as np

from batchsim.memory import Memory


def liveness_arrays(nworker: int) -> list[tuple[str, tuple[int, ...], str]]:
    return [
        ("beat", (nworker,), "i8"),  # per worker: ticks served
        ("worker.hung", (nworker,), "f8"),  # per worker: since when (epoch s) it has not ticked; 0: it does
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
