"""The snapshot protocol: what the loop publishes each control period, through shared memory.
Its writer (the physics process, `write_snapshot`) and its reader (a bridge worker,
`read_snapshot`) are both here; no rclpy.

Two buffers, seqlocked: snapshot n goes into buffer n % 2, whose `seq` reads 2n+1 while it
is written and 2n+2 when done, then `latest` says n. A reader copies its rows and checks
`seq` again: it retries a buffer being rewritten and never keeps a torn row. A worker woken
late reads the snapshot before the newest first where that one holds a channel the newest
does not (joint_states at 25 Hz in a 100 Hz loop are in one snapshot of four): a reader one
period late loses no message; two periods late, it does. Each channel
(ros_bridge/outputs.py) is copied only when some worker publishes from it this period
(`demand`, a recording's `rec.want`, the view's `view.want`); `written[c]` says which snapshot last wrote channel c.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from batchsim.memory import Memory


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
    b = n % 2
    m["seq"][b] = 2 * n + 1
    m["meta"][b] = (n, period, time, float(forced))
    m["status"][b] = status
    m["flags"][b] = flags
    demand = m["demand"].any(axis=0)
    for extra in ("rec.want", "view.want"):  # a recording's channels (protocol/recording.py), the view's
        if extra in m:
            demand = demand | m[extra].astype(bool)
    demand = demand.tolist()
    written = m["written"][b]
    for c, fill in enumerate(fills):
        if due[c] and (every_channel or demand[c]):
            fill(m[f"ch{c}"][b])
            written[c] = n
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

    With `catch_up`, the snapshot before the newest instead, where `snap` has not seen it
    and it holds a channel the newest does not: the next call then gives the newest."""
    m = memory
    latest, seq = m["latest"], m["seq"]
    for _ in range(8):
        n = int(latest[0])
        if n <= snap.n:
            return None
        if catch_up and n - 1 > snap.n:
            # unlocked look: a buffer rewritten meanwhile fails the seq checks below
            older, newest = m["written"][(n - 1) % 2], m["written"][n % 2]
            if ((older == n - 1) & (newest != n)).any():
                n -= 1
        b = n % 2
        if int(seq[b]) != 2 * n + 2:
            continue  # being rewritten: a newer one is coming
        meta = m["meta"][b].copy()
        status = m["status"][b, lo:hi].copy()
        flags = m["flags"][b, lo:hi].copy()
        written = m["written"][b].copy()
        channels = {
            c: m[f"ch{c}"][b, lo:hi].copy() for c in range(nchannel) if written[c] == n
        }
        if int(seq[b]) != 2 * n + 2:
            continue  # torn: the loop lapped us
        snap.n, snap.period, snap.time, snap.forced = n, int(meta[1]), float(meta[2]), bool(meta[3])
        snap.status, snap.flags, snap.written, snap.channels = status, flags, written, channels
        return snap
    return None
