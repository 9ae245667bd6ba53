"""The snapshot protocol: what the loop publishes each control period, through shared memory.
Its writer (the physics process, `write_snapshot`) and its reader (a bridge worker,
`read_snapshot`) are both here, with their shared arrays (`snapshot_arrays`); no rclpy.

A snapshot is a header (its number n, period index, sim time, forced; each world's status
and flags; which channels it wrote) and the rows of the channels it wrote. Headers go into a
ring of HEADERS buffers, snapshot n into buffer n % HEADERS, whose `seq` reads 2n+1 while it
is written and 2n+2 when done, then `latest` says n. A channel's rows go into the channel's
own SLOTS slots, its w-th write into slot w % SLOTS (`cseq[c, slot]`: 2w+1 while written,
2w+2 when done), so a snapshot that does not write a channel leaves its last rows alone. A reader
copies and checks the seqs again: it retries a header being rewritten and never keeps a
torn row. Each channel (ros_bridge/outputs.py) is written only when someone reads it this
period: a worker's subscribers or goals, a recording, the view (protocol/demand.py).

A worker woken late (`catch_up`) reads the oldest snapshot it has not seen that holds a
channel, then the next: joint_states at 25 Hz in a 100 Hz loop are in one snapshot of four,
and a worker that stalls for some periods (publishing 512 worlds' messages, their
/diagnostics, a garbage collection) still publishes each of them, in order, as long as its
header and that channel's rows were not overwritten since: up to HEADERS - 2 periods (300 ms
at 100 Hz), and before the channel's SLOTS-th next write (a 25 Hz channel: 230 ms). A worker
further behind than BACKLOG such snapshots cannot catch up (a fleet flat out, a worker with
more worlds than it can publish): it skips to the oldest snapshot holding a channel that no
later one holds, so that what it publishes stays fresh. A due snapshot lost either way is
counted (`missed joint_states` in /diagnostics).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from batchsim.memory import Memory
from ros_bridge.protocol.demand import demanded

# A 512-world worker is now and then late by more than 0.1 s (publishing its worlds, their
# /diagnostics): 32 headers and 6 slots hold 230 ms of a 25 Hz channel
HEADERS = 32  # snapshot headers kept: a reader HEADERS - 2 periods late still finds one
BACKLOG = 8  # snapshots holding a channel a late reader publishes one by one; beyond, it skips
SLOTS = 6  # each channel's rows kept: a channel's newest and the SLOTS - 1 before it


def snapshot_arrays(nworld: int, widths: Sequence[int]) -> list[tuple[str, tuple[int, ...], str]]:
    """The shared arrays of snapshots of `nworld` worlds with channels of these widths."""
    nch = max(1, len(widths))
    arrays: list[tuple[str, tuple[int, ...], str]] = [
        ("latest", (1,), "i8"),  # the newest complete snapshot
        ("seq", (HEADERS,), "i8"),  # per header: 2n+1 while snapshot n is written, 2n+2 when done
        ("meta", (HEADERS, 4), "f8"),  # per header: snapshot n, period index, sim time, forced
        ("status", (HEADERS, nworld), "u1"),  # Status bits, the bridge's BAD_COMMAND included
        ("flags", (HEADERS, nworld), "u1"),  # FLAG_* bits
        ("written", (HEADERS, nch), "i8"),  # per header and channel: n if it wrote the channel, else -1
        ("cwrite", (HEADERS, nch), "i8"),  # ... and which write of the channel that was
        ("cseq", (nch, SLOTS), "i8"),  # per channel and slot: 2w+1 while its write w goes in, 2w+2 done
        ("cwrites", (nch,), "i8"),  # per channel: its writes so far
    ]
    arrays += [(f"ch{c}", (SLOTS, nworld, width), "f8") for c, width in enumerate(widths)]
    return arrays


def reset_snapshots(memory: Memory) -> None:
    """No snapshot yet."""
    memory["latest"][0] = -1
    memory["written"][:] = -1


def channel_rows(memory: Memory, n: int, c: int) -> np.ndarray | None:
    """Channel c's rows as snapshot n wrote them (nworld, width), a view; None where n did
    not write c. For the writer's own process (no check against a concurrent write)."""
    b = n % HEADERS
    if int(memory["written"][b, c]) != n:
        return None
    return memory[f"ch{c}"][int(memory["cwrite"][b, c]) % SLOTS]


def write_snapshot(
    memory: Memory,
    n: int,
    period: int,
    time: float,
    forced: bool,
    status: np.ndarray,
    flags: np.ndarray,
    fills: Sequence[Callable[[np.ndarray], None]],
    due: Sequence[bool],
    every_channel: bool = False,
) -> int:
    """Write snapshot `n`: status and flags `(nworld,)`, and each channel `c` a worker demands
    (every one with `every_channel`) whose `due[c]` is true, by `fills[c](out)`. Returns n."""
    m = memory
    b = n % HEADERS
    m["seq"][b] = 2 * n + 1
    m["meta"][b] = (n, period, time, float(forced))
    m["status"][b] = status
    m["flags"][b] = flags
    demand = demanded(m).tolist()
    written, cwrite, cseq, cwrites = m["written"][b], m["cwrite"][b], m["cseq"], m["cwrites"]
    for c, fill in enumerate(fills):
        if due[c] and (every_channel or demand[c]):
            w = int(cwrites[c])
            cseq[c, w % SLOTS] = 2 * w + 1
            fill(m[f"ch{c}"][w % SLOTS])
            cseq[c, w % SLOTS] = 2 * w + 2
            cwrites[c] = w + 1
            written[c], cwrite[c] = n, w
        else:
            written[c] = -1
    m["seq"][b] = 2 * n + 2
    m["latest"][0] = n
    return n


class Snapshot:
    """This worker's rows of one snapshot, copied out of shared memory."""

    __slots__ = ("n", "period", "time", "forced", "status", "flags", "channels", "written")

    def __init__(self) -> None:
        self.n = -1
        self.period = 0
        self.time = 0.0
        self.forced = False
        self.status = np.zeros(0, np.uint8)
        self.flags = np.zeros(0, np.uint8)
        self.channels: dict[int, np.ndarray] = {}
        self.written = np.zeros(0, np.int64)


def read_snapshot(
    memory: Memory, nchannel: int, lo: int, hi: int, snap: Snapshot, catch_up: bool = False
) -> Snapshot | None:
    """Rows lo..hi-1 of the newest snapshot into `snap`, if newer than it; None otherwise.

    With `catch_up`, the oldest snapshot `snap` has not seen that holds a channel, where there
    is one still kept and no more than BACKLOG such wait (more: the oldest holding a channel
    no later one holds): the next calls give the later ones. A channel whose rows were
    overwritten meanwhile is left out of `snap.channels`."""
    m = memory
    latest, seq = m["latest"], m["seq"]
    for _ in range(8):
        n = int(latest[0])
        if n <= snap.n:
            return None
        if catch_up and n - 1 > snap.n:
            n = _oldest_needed(m, n, max(snap.n + 1, n - HEADERS + 2))
        b = n % HEADERS
        if int(seq[b]) != 2 * n + 2:
            continue  # being rewritten: a newer one is coming
        meta = m["meta"][b].copy()
        status = m["status"][b, lo:hi].copy()
        flags = m["flags"][b, lo:hi].copy()
        written = m["written"][b].copy()
        cwrite = m["cwrite"][b].copy()
        if int(seq[b]) != 2 * n + 2:
            continue  # torn: the loop lapped us
        channels = {}
        for c in range(nchannel):
            if written[c] == n:
                w = int(cwrite[c])
                rows = m[f"ch{c}"][w % SLOTS, lo:hi].copy()
                if int(m["cseq"][c, w % SLOTS]) == 2 * w + 2:  # not overwritten while copied, nor before
                    channels[c] = rows
        snap.n, snap.period, snap.time, snap.forced = n, int(meta[1]), float(meta[2]), bool(meta[3])
        snap.status, snap.flags, snap.written, snap.channels = status, flags, written, channels
        return snap
    return None


def _oldest_needed(m: Memory, n: int, first: int) -> int:
    """The oldest of snapshots first..n-1 holding a channel, if no more than BACKLOG do; else
    the oldest holding a channel none after it holds; n if none. Unlocked looks: a header
    rewritten meanwhile fails read_snapshot's seq checks."""
    written = m["written"]
    holding = [k for k in range(first, n) if (written[k % HEADERS] == k).any()]
    if len(holding) <= BACKLOG:
        return holding[0] if holding else n
    held = written[n % HEADERS] == n  # channels a later snapshot holds
    pick = n
    for k in reversed(holding):
        mine = written[k % HEADERS] == k
        if (mine & ~held).any():
            pick = k
        held |= mine
    return pick
