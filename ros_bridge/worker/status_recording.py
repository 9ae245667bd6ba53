"""The recorded worlds' status in a recording: `/diagnostics` (diagnostic_msgs/DiagnosticArray),
one DiagnosticStatus per world as the live /diagnostics words it (ros_bridge/world_status.py),
with its rejected commands in all and the last one's reason (`bad_commands`, `last_problem`,
read from the bridge's shared memory as the live one reads them), without the counts only each
live worker keeps (rejections per topic and reason, messages published).

Every world is written at the first period and once a sim second after, as a diagnostic
updater publishes; in between, a period in which some worlds' status bits or flags changed
writes those worlds, stamped with that period's sim time, so a world that froze or took a
bad command is in the file at the period it happened (`batchsim view FILE` colours the
worlds from these).
"""

from __future__ import annotations

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.serialization import serialize_message

from ros_bridge import world_status
from ros_bridge.protocol.commands import RejectionWriter, bad_commands

TOPIC, MSG_TYPE = "/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"
FULL_EVERY = 1.0  # sim seconds between two arrays of every world


class StatusRecording:
    """/diagnostics for the recorded worlds named `namespaces`; `rejections`: the bridge's
    rejection blocks (`rej`, `hrej`) and each recorded world's row in them (None: no counts)."""

    def __init__(
        self, namespaces: list[str], rejections: tuple[RejectionWriter, RejectionWriter, np.ndarray] | None = None
    ):
        self.namespaces = namespaces
        self.rejections = rejections
        self._bits = np.zeros(len(namespaces), np.int64) - 1  # nothing written yet
        self._flags = np.zeros(len(namespaces), np.int64)
        self._bad = np.zeros(len(namespaces), np.int64)
        self._next_full = -np.inf
        self._made: dict[tuple[int, int, int], DiagnosticStatus] = {}  # (row, bits, flags) -> its status, none rejected

    def message(self, time: float, sec: int, nanosec: int, status: np.ndarray, flags: np.ndarray) -> bytes | None:
        """This period's DiagnosticArray, serialized, or None when no world changed and no full one is due."""
        bad = self._bad
        if self.rejections is not None:
            mine, host, worlds = self.rejections
            bad = mine.count[worlds] + host.count[worlds]
        if time >= self._next_full:
            rows = np.arange(len(self.namespaces))
            self._next_full = (np.floor(time / FULL_EVERY) + 1) * FULL_EVERY
        else:
            rows = np.flatnonzero((status != self._bits) | (flags != self._flags) | (bad != self._bad))
            if not rows.size:
                return None
        self._bits[rows], self._flags[rows], self._bad[rows] = status[rows], flags[rows], bad[rows]
        out = DiagnosticArray()
        out.header.stamp.sec, out.header.stamp.nanosec = sec, nanosec
        out.status = [self._status(r, int(status[r]), int(flags[r])) for r in rows.tolist()]
        return bytes(serialize_message(out))

    def _status(self, row: int, bits: int, flags: int) -> DiagnosticStatus:
        count, last = 0, ""
        if self.rejections is not None:
            mine, host, worlds = self.rejections
            count, last = bad_commands(mine, host, worlds[row])
        key = (row, bits, flags)
        made = self._made.get(key) if not count else None
        if made is None:
            ns = self.namespaces[row]
            made = DiagnosticStatus(
                level=bytes([world_status.level(bits, flags)]),  # a ROS byte field
                name=world_status.status_name(ns),
                message=world_status.message(bits, flags, last),
                hardware_id=ns,
                values=[KeyValue(key=k, value=v) for k, v in world_status.values(bits, flags)]
                + [KeyValue(key="bad_commands", value=str(count)), KeyValue(key="last_problem", value=last)],
            )
            if not count:
                self._made[key] = made
        return made
