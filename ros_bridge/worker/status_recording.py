"""The recorded worlds' status in a recording: `/diagnostics` (diagnostic_msgs/DiagnosticArray),
one DiagnosticStatus per world as the live /diagnostics words it (ros_bridge/world_status.py),
without the counts only the live bridge keeps (rejections, messages published).

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

TOPIC, MSG_TYPE = "/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"
FULL_EVERY = 1.0  # sim seconds between two arrays of every world


class StatusRecording:
    """/diagnostics for the recorded worlds named `namespaces`."""

    def __init__(self, namespaces: list[str]):
        self.namespaces = namespaces
        self._bits = np.zeros(len(namespaces), np.int64) - 1  # nothing written yet
        self._flags = np.zeros(len(namespaces), np.int64)
        self._next_full = -np.inf
        self._made: dict[tuple[int, int, int], DiagnosticStatus] = {}  # (row, bits, flags) -> its status

    def message(self, time: float, sec: int, nanosec: int, status: np.ndarray, flags: np.ndarray) -> bytes | None:
        """This period's DiagnosticArray, serialized, or None when no world changed and no full one is due."""
        if time >= self._next_full:
            rows = np.arange(len(self.namespaces))
            self._next_full = (np.floor(time / FULL_EVERY) + 1) * FULL_EVERY
        else:
            rows = np.flatnonzero((status != self._bits) | (flags != self._flags))
            if not rows.size:
                return None
        self._bits[rows], self._flags[rows] = status[rows], flags[rows]
        out = DiagnosticArray()
        out.header.stamp.sec, out.header.stamp.nanosec = sec, nanosec
        out.status = [self._status(r, int(status[r]), int(flags[r])) for r in rows.tolist()]
        return bytes(serialize_message(out))

    def _status(self, row: int, bits: int, flags: int) -> DiagnosticStatus:
        key = (row, bits, flags)
        made = self._made.get(key)
        if made is None:
            ns = self.namespaces[row]
            made = self._made[key] = DiagnosticStatus(
                level=bytes([world_status.level(bits, flags)]),  # a ROS byte field
                name=world_status.status_name(ns),
                message=world_status.message(bits, flags),
                hardware_id=ns,
                values=[KeyValue(key=k, value=v) for k, v in world_status.values(bits, flags)],
            )
        return made
