"""The recorder's side of the input rings (ros_bridge/protocol/input_ring.py): every period's
physics inputs as `/batchsim/inputs` and the worlds' (re)starts as `/batchsim/starts`, each a
std_msgs/Float64MultiArray packed by batchsim.resim.layout, and the controllers' inputs as
`/batchsim/controller_inputs` (std_msgs/String, a JSON document each), stamped with the period's
sim time."""

from __future__ import annotations

import json
from collections.abc import Callable

import numpy as np

from batchsim.memory import Memory, Ring
from batchsim.resim.layout import (
    EVENTS_TOPIC,
    EVENTS_TYPE,
    INPUTS_TOPIC,
    MSG_TYPE,
    STARTS_TOPIC,
    pack,
    pack_string,
)
from ros_bridge.protocol.input_ring import EVENTS, INPUTS, STARTS, RowRing
from ros_bridge.worker.messages import stamp_of


class InputTopics:
    """Takes the rings' entries and writes them (`add(channel, t, data)`); `nrow` recorded worlds."""

    def __init__(self, memory: Memory, nrow: int, channel: Callable[..., int], add: Callable[[int, int, bytes], None]):
        self._inputs, self._starts = RowRing(memory, INPUTS), RowRing(memory, STARTS)
        self._events, self._dropped = Ring(memory, EVENTS), memory[f"{EVENTS}.dropped"]
        self._nrow, self._add = nrow, add
        self._input_channel = channel(INPUTS_TOPIC, MSG_TYPE, depth=1000)
        self._start_channel = channel(STARTS_TOPIC, MSG_TYPE, depth=100)
        self._event_channel = channel(EVENTS_TOPIC, EVENTS_TYPE, depth=100)
        self._held: list[tuple[np.ndarray, np.ndarray]] = []  # start rows of a period still filling
        self._last = -1.0  # the newest period whose inputs were written

    def take(self, final: bool = False) -> None:
        """The periods' inputs written so far, and the starts grouped per period, one message each.
        A period's starts go into the ring before its inputs, so those of a period whose inputs
        were taken are complete (`final`: every one held)."""
        held = self._starts.take(1)  # first: a period's inputs taken below have their starts in here
        for header, rows in self._inputs.take(self._nrow):
            self._last = header[0]
            self._add(self._input_channel, _stamp(header), pack(header, rows))
        self._held += held
        for _kind, payload in self._events.take():
            text = payload.tobytes().rstrip(b"\x00").decode()
            sec, nanosec = stamp_of(json.loads(text)["time"])
            self._add(self._event_channel, sec * 1_000_000_000 + nanosec, pack_string(text))
        while self._held and (final or self._held[0][0][0] <= self._last):
            first = self._held[0][0][0]
            same = [e for e in self._held if e[0][0] == first]
            self._add(self._start_channel, _stamp(same[0][0]), pack(same[0][0], np.concatenate([r for _, r in same])))
            self._held = self._held[len(same) :]

    def lost_line(self) -> str:
        """What the rings dropped (the recorder fell behind), as the end of the recorder's last line."""
        lost = self._inputs.dropped() + self._starts.dropped()
        line = f"; {lost} periods' inputs dropped (those worlds cannot be re-run past them)" if lost else ""
        events = int(self._dropped[0])
        return line + (f"; {events} controller inputs dropped (the controllers cannot be re-run past them)" if events else "")


def _stamp(header: np.ndarray) -> int:
    """A period's sim time, in ns (the messages' log time, as the other topics' stamps)."""
    sec, nanosec = stamp_of(float(header[1]))
    return sec * 1_000_000_000 + nanosec
