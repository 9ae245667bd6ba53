"""The recorder's side of the input rings (ros_bridge/protocol/input_ring.py): every period's
physics inputs as `/batchsim/inputs` and the worlds' (re)starts as `/batchsim/starts`, each a
std_msgs/Float64MultiArray packed by batchsim.resim.layout, and the controllers' inputs as
`/batchsim/controller_inputs` (std_msgs/String, a JSON document each), stamped with the period's
sim time. In a fleet of several groups, each group's under `/batchsim/<group>/`."""

from __future__ import annotations

import json
from collections.abc import Callable

import numpy as np

from batchsim.memory import Memory, Ring
from batchsim.resim.layout import EVENTS_TYPE, MSG_TYPE, ResimNames, pack, pack_string
from batchsim.stamps import stamp_ns
from ros_bridge.protocol.input_ring import EVENTS, INPUTS, STARTS, RowRing


class InputTopics:
    """Takes the rings' entries and writes them (`add(channel, t, data)`) on the topics `names`
    (one group's: batchsim.resim.layout.resim_names); `nrow` recorded worlds.

    The file is in log-time order (a replay paces by it, and a reader that reads it through
    relies on it), so an entry is written only once nothing older can follow it: `take(upto)`
    writes those stamped at or before `upto`, the period the recorder writes next. A period's
    inputs and starts go into their rings before its snapshot goes into the recording ring,
    so those of every period the recorder has are in hand by then."""

    def __init__(
        self, memory: Memory, nrow: int, channel: Callable[..., int], add: Callable[[int, int, bytes], None], names: ResimNames
    ):
        self._inputs, self._starts = RowRing(memory, INPUTS), RowRing(memory, STARTS)
        self._events, self._dropped = Ring(memory, EVENTS), memory[f"{EVENTS}.dropped"]
        self._nrow, self._add = nrow, add
        self._input_channel = channel(names.inputs, MSG_TYPE, depth=1000)
        self._start_channel = channel(names.starts, MSG_TYPE, depth=100)
        self._event_channel = channel(names.events, EVENTS_TYPE, depth=100)
        self._held_inputs: list[tuple[np.ndarray, np.ndarray]] = []  # taken from the rings, not yet written
        self._held_starts: list[tuple[np.ndarray, np.ndarray]] = []  # one row each: a period's are one message
        self._held_events: list[tuple[int, str]] = []  # (stamp ns, JSON document)

    def take(self, upto: int | None = None) -> None:
        """The rings' entries taken, and those stamped at or before `upto` (ns; None: every one,
        the recording's end) written in stamp order: a period's starts as one message."""
        self._held_starts += self._starts.take(1)
        self._held_inputs += self._inputs.take(self._nrow)
        for _kind, payload in self._events.take():
            text = payload.tobytes().rstrip(b"\x00").decode()
            self._held_events.append((stamp_ns(json.loads(text)["time"]), text))
        due = lambda stamp: upto is None or stamp <= upto  # noqa: E731
        out: list[tuple[int, int, int, bytes]] = []  # (stamp, rank, channel, data): sorted, written
        starts: dict[float, list[tuple[np.ndarray, np.ndarray]]] = {}
        for entry in self._held_starts:
            starts.setdefault(float(entry[0][0]), []).append(entry)
        self._held_starts = []
        for same in starts.values():
            stamp = _stamp(same[0][0])
            if due(stamp):
                out.append((stamp, 0, self._start_channel, pack(same[0][0], np.concatenate([r for _, r in same]))))
            else:
                self._held_starts += same
        held = self._held_inputs
        n = next((k for k, (header, _) in enumerate(held) if not due(_stamp(header))), len(held))
        out += [(_stamp(header), 1, self._input_channel, pack(header, rows)) for header, rows in held[:n]]
        self._held_inputs = held[n:]
        events = self._held_events
        n = next((k for k, (stamp, _) in enumerate(events) if not due(stamp)), len(events))
        out += [(stamp, 2, self._event_channel, pack_string(text)) for stamp, text in events[:n]]
        self._held_events = events[n:]
        out.sort(key=lambda e: (e[0], e[1]))  # stable: each topic's own order kept
        for stamp, _, channel, data in out:
            self._add(channel, stamp, data)

    def lost_line(self) -> str:
        """What the rings dropped (the recorder fell behind), as the end of the recorder's last line."""
        lost = self._inputs.dropped() + self._starts.dropped()
        line = f"; {lost} periods' inputs dropped (those worlds cannot be re-run past them)" if lost else ""
        events = int(self._dropped[0])
        return line + (f"; {events} controller inputs dropped (the controllers cannot be re-run past them)" if events else "")


def _stamp(header: np.ndarray) -> int:
    """A period's sim time, in ns (the messages' log time, as the other topics' stamps)."""
    return stamp_ns(float(header[1]))
