"""The recording's input rings: every control period's physics inputs of the recorded worlds, and
their (re)starts, queued in shared memory for the recorder (batchsim.resim says what they hold).

Unlike the snapshot's ring (recording.py), which takes the periods the bridge publishes, these
take every period: re-simulation needs each one. A ring `name` is `{name}.pos` (entries written,
ever; entries read), `{name}.dropped`, `{name}.meta` (slots, 3: period number, sim time, physics
steps) and `{name}.rows` (slots, rows per entry, width). The writer (the physics process) never
waits, except where `--rtf 0` asks for every period (Recording waits while `full()`); an entry
that finds the ring full is counted in `dropped` and skipped.
"""

from __future__ import annotations

import numpy as np

from batchsim.memory import Memory
from batchsim.memory import ring_arrays as byte_ring_arrays
from ros_bridge.protocol.recording import MAX_SLOTS, MIN_SLOTS, RING_BYTES

INPUTS, STARTS, EVENTS = "rin", "rst", "rev"  # EVENTS: a byte ring (batchsim.memory.Ring) of JSON documents
EVENT_BYTES = 8 << 20


def ring_arrays(name: str, rows: int, width: int, least: int = MIN_SLOTS) -> list[tuple[str, tuple[int, ...], str]]:
    """The Layout entries of ring `name`: entries of `rows` x `width` float64, at least `least` of them."""
    slots = int(max(least, min(MAX_SLOTS, RING_BYTES // (8 * (3 + rows * width)))))
    return [
        (f"{name}.pos", (2,), "i8"),
        (f"{name}.dropped", (1,), "i8"),
        (f"{name}.meta", (slots, 3), "f8"),
        (f"{name}.rows", (slots, max(1, rows), max(1, width)), "f8"),
    ]


class RowRing:
    """One ring, either side: `put` (the physics process), `take` (the recorder)."""

    def __init__(self, memory: Memory, name: str):
        self.pos, self.dropped_ = memory[f"{name}.pos"], memory[f"{name}.dropped"]
        self.meta, self.rows = memory[f"{name}.meta"], memory[f"{name}.rows"]
        self.slots = len(self.meta)

    def full(self) -> bool:
        return int(self.pos[0]) - int(self.pos[1]) >= self.slots

    def put(self, header: tuple[float, float, float], rows: np.ndarray) -> bool:
        """One entry (rows: (k, width), k up to the ring's rows per entry); False: dropped (full)."""
        if self.full():
            self.dropped_[0] += 1
            return False
        k = int(self.pos[0])
        s = k % self.slots
        self.meta[s] = header
        self.rows[s, : len(rows)] = rows
        self.pos[0] = k + 1
        return True

    def restart(self) -> None:
        """A new recording: emptied, none dropped."""
        self.pos[1] = self.pos[0]
        self.dropped_[0] = 0

    def pending(self) -> int:
        return int(self.pos[0]) - int(self.pos[1])

    def dropped(self) -> int:
        return int(self.dropped_[0])

    def take(self, nrow: int, most: int = 1024) -> list[tuple[np.ndarray, np.ndarray]]:
        """Up to `most` entries, (header (3,), rows (nrow, width)) copies, in order; their room handed back."""
        read, write = int(self.pos[1]), int(self.pos[0])
        out = []
        for k in range(read, min(write, read + most)):
            s = k % self.slots
            out.append((self.meta[s].copy(), self.rows[s, :nrow].copy()))
        self.pos[1] = read + len(out)
        return out


def event_arrays() -> list[tuple[str, tuple[int, ...], str]]:
    """The event ring's Layout entries: its bytes, and how many documents found it full."""
    return [*byte_ring_arrays(EVENTS, EVENT_BYTES), (f"{EVENTS}.dropped", (1,), "i8")]
