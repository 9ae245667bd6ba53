"""A worker's per-world outputs over its rows of the loop's snapshot (ros_bridge/protocol/snapshot.py).

An `Output` is one OutputSpec over the worker's worlds: its publishers (created at start or
on request) and its messages as bulk CDR bytes.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ros_bridge.plan import OutputSpec
from ros_bridge.worker.messages import BulkMessages, message_type


class Output:
    """One OutputSpec over this worker's worlds: publishers (None until created), bulk bytes."""

    def __init__(self, spec: OutputSpec, namespaces: list[str]):
        self.spec = spec
        self.namespaces = namespaces
        self._bulk: BulkMessages | None = None
        self.publishers: list[Any] = [None] * len(namespaces)
        self._rows: list[int] = []
        self._last_period: int | None = None  # the period of the last snapshot published on schedule
        self.msg_type = message_type(spec.msg_type)
        # per field: (channel, columns with -1 clipped, the columns that are -1)
        self.gather = [
            (f.channel, np.maximum(np.array(f.columns, dtype=np.intp), 0), np.array(f.columns) < 0) for f in spec.fields
        ]

    @property
    def rows(self) -> list[int]:
        """The worlds (rows) with a subscriber."""
        return self._rows

    @rows.setter
    def rows(self, rows: list[int]) -> None:
        if not self._rows:  # published again after a pause: nothing was missed meanwhile
            self._last_period = None
        self._rows = rows

    def missed(self, snap: Any) -> int:
        """The periods this output was due in (multiples of spec.every) between its last
        scheduled publication and snapshot `snap`'s, none of which it published: their
        snapshots were overwritten before this worker read them (ros_bridge/protocol/snapshot.py).
        Records `snap` as the last; a forced snapshot (out of schedule) counts nothing."""
        if snap.forced:
            return 0
        last, self._last_period = self._last_period, snap.period
        if last is None or snap.period <= last:
            return 0
        every = self.spec.every
        return (snap.period - 1) // every - last // every

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
