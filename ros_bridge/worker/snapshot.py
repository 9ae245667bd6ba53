"""What a worker reads of the loop's snapshot, and its per-world outputs over those rows.

The loop writes a snapshot per control period into one of two buffers (seqlocked: a
reader retries a buffer being rewritten, never reads a torn row); `read_snapshot` copies
a worker's rows of the newest one. An `Output` is one OutputSpec over the worker's worlds:
its publishers (created at start or on request) and its messages as bulk CDR bytes.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from batchsim.memory import Memory
from ros_bridge.plan import OutputSpec
from ros_bridge.worker.messages import BulkMessages, message_type


class Output:
    """One OutputSpec over this worker's worlds: publishers (None until created), bulk bytes."""

    def __init__(self, spec: OutputSpec, namespaces: list[str]):
        self.spec = spec
        self.namespaces = namespaces
        self._bulk: BulkMessages | None = None
        self.publishers: list[Any] = [None] * len(namespaces)
        self.rows: list[int] = []  # the worlds (rows) with a subscriber
        self.msg_type = message_type(spec.msg_type)
        # per field: (channel, columns with -1 clipped, the columns that are -1)
        self.gather = [
            (f.channel, np.maximum(np.array(f.columns, dtype=np.intp), 0), np.array(f.columns) < 0) for f in spec.fields
        ]

    @property
    def bulk(self) -> BulkMessages:
        """The serialized messages, laid out when first published (most outputs never are)."""
        if self._bulk is None:
            self._bulk = BulkMessages(self.spec, self.namespaces)
        return self._bulk

    def values(self, channels: dict[int, np.ndarray]) -> np.ndarray:
        parts = []
        for ch, cols, nan in self.gather:
            v = channels[ch][:, cols]
            if nan.any():
                v[:, nan] = np.nan
            parts.append(v)
        return np.concatenate(parts, axis=1) if len(parts) > 1 else parts[0]


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


def read_snapshot(memory: Memory, nchannel: int, lo: int, hi: int, snap: Snapshot) -> Snapshot | None:
    """Rows lo..hi-1 of the newest snapshot into `snap`, if newer than it; None otherwise."""
    m = memory
    latest, seq = m["latest"], m["seq"]
    for _ in range(8):
        n = int(latest[0])
        if n <= snap.n:
            return None
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
