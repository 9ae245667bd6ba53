"""The recording protocol: every snapshot the loop writes, queued for the recorder process
(ros_bridge/worker/recorder.py), through shared memory. Its writer (the physics process,
`RecordWriter`) and its reader (the recorder, `RecordReader`) are both here; no rclpy.

The snapshot (snapshot.py) keeps only the newest period, which is right for publishing and
wrong for a file that must hold every period. So while a recording runs, each snapshot's
recorded rows (the recorded worlds of the recorded channels) are also copied into a ring of
`slots` periods: the writer owns `rec.pos[0]` (periods written, ever), the reader
`rec.pos[1]` (periods read); slot k holds period k % slots, and is visible once pos[0]
has passed it. The writer never waits on the reader (the loop must not slow down, except
where `--rtf 0` asks for every period as fast as the recorder takes them): a period that
finds the ring full is counted in `rec.dropped` and skipped.

`rec.on` says a recording runs (set by the physics process from the start it is asked
for, before the recorder is up: the ring holds the periods until it reads them; cleared by
either side when it ends: `set_recording`, `recording`); `rec.want` says which channels the
recorder needs written into the snapshot (demand.py ORs it into the workers' demand). A recording is started and stopped through a mailbox:
worker 0's `/batchsim/record` service writes `rec.req` (ticket, on), the physics process
answers in `rec.ans` (ticket, ok) and `rec.msg` (its message).
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from batchsim.memory import Memory
from ros_bridge.protocol.demand import ChannelDemand
from ros_bridge.protocol.snapshot import HEADERS, channel_rows
from ros_bridge.protocol.text import put_text, text_of

RING_BYTES = 32 << 20  # the ring's size, at most (pages are taken only as a recording writes them)
MIN_SLOTS, MAX_SLOTS = 16, 4096
MESSAGE = 512  # bytes of the answer's message


def ring_slots(nrow: int, widths: Sequence[int]) -> int:
    """Periods the ring holds: as many as fit in RING_BYTES, within MIN_SLOTS..MAX_SLOTS."""
    per_slot = 8 * nrow * max(1, sum(widths)) + 2 * nrow + 64
    return int(min(MAX_SLOTS, max(MIN_SLOTS, RING_BYTES // per_slot)))


def recording_arrays(
    nchannel: int, nrow: int, channels: Sequence[int], widths: Sequence[int]
) -> list[tuple[str, tuple[int, ...], str]]:
    """The Layout entries: `nrow` recorded worlds of the recorded `channels` (their `widths`)."""
    slots = ring_slots(nrow, widths)
    arrays: list[tuple[str, tuple[int, ...], str]] = [
        ("rec.on", (1,), "i8"),
        ("rec.pos", (2,), "i8"),
        ("rec.dropped", (1,), "i8"),
        ("rec.want", (max(1, nchannel),), "u1"),
        ("rec.req", (3,), "i8"),  # ticket, 1 to start / 0 to stop, when it was asked (monotonic ns)
        ("rec.ans", (2,), "i8"),  # ticket answered, 1 when it succeeded
        ("rec.msg", (MESSAGE,), "u1"),
        ("rec.meta", (slots, 4), "f8"),  # snapshot n, period, sim time, forced
        ("rec.flags", (slots, max(1, nrow)), "u1"),
        ("rec.status", (slots, max(1, nrow)), "u1"),  # the worlds' Status bits, for /diagnostics
        ("rec.written", (slots, max(1, len(channels))), "u1"),
    ]
    for c, width in zip(channels, widths, strict=True):
        arrays.append((f"rec.ch{c}", (slots, max(1, nrow), width), "f8"))
    return arrays


class RecordWriter:
    """The physics process's side: copy each new snapshot's recorded rows into the ring."""

    def __init__(self, memory: Memory, channels: Sequence[int], worlds: np.ndarray):
        self.m = memory
        self.channels = list(channels)
        self.worlds = worlds
        self.slots = memory["rec.meta"].shape[0]
        self._last = -1  # the newest snapshot copied

    def full(self) -> bool:
        pos = self.m["rec.pos"]
        return int(pos[0]) - int(pos[1]) >= self.slots

    def put_newest(self) -> bool:
        """Copy the newest snapshot if it is new; False if it was dropped (the ring was full)."""
        m = self.m
        n = int(m["latest"][0])
        if n <= self._last or n < 0:
            return True
        self._last = n
        if self.full():
            m["rec.dropped"][0] += 1
            return False
        b = n % HEADERS
        k = int(m["rec.pos"][0])
        s = k % self.slots
        m["rec.meta"][s] = m["meta"][b]
        nrow = len(self.worlds)  # 0: a fleet's first group that leads the others' recording, /clock alone
        m["rec.flags"][s, :nrow] = m["flags"][b, self.worlds]
        m["rec.status"][s, :nrow] = m["status"][b, self.worlds]
        for j, c in enumerate(self.channels):
            rows = channel_rows(m, n, c)
            m["rec.written"][s, j] = rows is not None
            if rows is not None:
                np.take(rows, self.worlds, axis=0, out=m[f"rec.ch{c}"][s, :nrow])
        m["rec.pos"][0] = k + 1
        return True

    def restart(self) -> None:
        """A new recording: the ring emptied (of what a killed recorder left), none dropped yet,
        and the next snapshot its first (not one written before the recording began)."""
        self.m["rec.pos"][1] = self.m["rec.pos"][0]
        self.m["rec.dropped"][0] = 0
        self._last = int(self.m["latest"][0])


class RecordedPeriod:
    """One period out of the ring: its meta, flags and status bits (nrow,), and per recorded
    channel its rows."""

    __slots__ = ("n", "period", "time", "forced", "flags", "status", "channels")

    def __init__(
        self, meta: np.ndarray, flags: np.ndarray, channels: dict[int, np.ndarray], status: np.ndarray | None = None
    ):
        self.n, self.period, self.time, self.forced = (
            int(meta[0]),
            int(meta[1]),
            float(meta[2]),
            bool(meta[3]),
        )
        self.flags = flags
        self.status = np.zeros_like(flags) if status is None else status
        self.channels = channels


class RecordReader:
    """The recorder's side: take the periods written so far, in order."""

    def __init__(self, memory: Memory, channels: Sequence[int]):
        self.m = memory
        self.channels = list(channels)
        self.slots = memory["rec.meta"].shape[0]

    def pending(self) -> int:
        pos = self.m["rec.pos"]
        return int(pos[0]) - int(pos[1])

    def dropped(self) -> int:
        """Periods the writer found no room for."""
        return int(self.m["rec.dropped"][0])

    def take(self, most: int = 256) -> list[RecordedPeriod]:
        """Up to `most` periods (copies), and the ring's room for them handed back."""
        m = self.m
        read, write = int(m["rec.pos"][1]), int(m["rec.pos"][0])
        out = []
        for k in range(read, min(write, read + most)):
            s = k % self.slots
            written = m["rec.written"][s]
            channels = {c: m[f"rec.ch{c}"][s].copy() for j, c in enumerate(self.channels) if written[j]}
            out.append(
                RecordedPeriod(m["rec.meta"][s].copy(), m["rec.flags"][s].copy(), channels, m["rec.status"][s].copy())
            )
        m["rec.pos"][1] = read + len(out)
        return out


class GroupsReader:
    """The rings of a fleet's groups (each group's RecordReader, batchsim.fleet.groups), taken as
    one stream of (group, period) in sim-time order: one loop writes every group's ring each
    period, but the recorder reads them in turn, and a file's messages go in time order (a replay
    paces by it). A period is handed out once every ring has reached its sim time (or `final`),
    each ring's periods in their order; at most HOLD periods wait for a ring that fell behind."""

    HOLD = 4096

    def __init__(self, readers: Sequence[RecordReader]):
        self.readers = list(readers)
        self._held: list[list[RecordedPeriod]] = [[] for _ in self.readers]
        self._newest = [-np.inf] * len(self.readers)

    def pending(self) -> bool:
        """Whether a ring holds periods not yet taken."""
        return any(r.pending() for r in self.readers)

    def dropped(self) -> int:
        return sum(r.dropped() for r in self.readers)

    def take(self, final: bool = False) -> list[tuple[int, RecordedPeriod]]:
        """The periods every ring has reached, in sim-time order; with `final`, every one held."""
        if len(self.readers) == 1:
            return [(0, p) for p in self.readers[0].take()]
        for k, reader in enumerate(self.readers):
            periods = reader.take()
            if periods:
                self._held[k] += periods
                self._newest[k] = max(self._newest[k], periods[-1].time)
        held = sum(len(h) for h in self._held)
        horizon = np.inf if final or held > self.HOLD else min(self._newest)
        out: list[tuple[int, RecordedPeriod]] = []
        heads = [0] * len(self._held)
        while True:
            due = [(h[i].time, k) for k, (h, i) in enumerate(zip(self._held, heads, strict=True)) if i < len(h)]
            if not due or min(due)[0] > horizon:
                break
            _, k = min(due)
            out.append((k, self._held[k][heads[k]]))
            heads[k] += 1
        self._held = [h[i:] for h, i in zip(self._held, heads, strict=True)]
        return out


def set_recording(memory: Memory, channels: Sequence[int] | None) -> None:
    """A recording runs from now, the snapshot writing `channels` for it; None: none runs."""
    if channels is None:
        memory["rec.on"][0] = 0
        ChannelDemand(memory, "rec.want").clear()
    else:
        ChannelDemand(memory, "rec.want").set(channels)
        memory["rec.on"][0] = 1


def recording(memory: Memory) -> bool:
    """Whether a recording runs."""
    return bool(memory["rec.on"][0])


def next_ticket(memory: Memory) -> int:
    """Worker 0: the ticket of its next request."""
    return int(memory["rec.req"][0]) + 1


def put_request(memory: Memory, ticket: int, on: bool) -> None:
    """Worker 0: ask for a recording to start (`on`) or stop."""
    memory["rec.req"][1] = int(on)
    memory["rec.req"][2] = time.monotonic_ns()  # CLOCK_MONOTONIC: one clock for every process of the host
    memory["rec.req"][0] = ticket


def take_request(memory: Memory, answered: int) -> tuple[int, bool, float] | None:
    """The physics process: a request newer than `answered`, as (ticket, on, its age in s)."""
    ticket = int(memory["rec.req"][0])
    if ticket <= answered:
        return None
    return ticket, bool(memory["rec.req"][1]), (time.monotonic_ns() - int(memory["rec.req"][2])) * 1e-9


def put_answer(memory: Memory, ticket: int, ok: bool, message: str) -> None:
    put_text(memory["rec.msg"], message)
    memory["rec.ans"][1] = int(ok)
    memory["rec.ans"][0] = ticket


def answer(memory: Memory, ticket: int) -> tuple[bool, str] | None:
    """Worker 0: the answer to `ticket`, once given."""
    if int(memory["rec.ans"][0]) != ticket:
        return None
    return bool(memory["rec.ans"][1]), text_of(memory["rec.msg"])
