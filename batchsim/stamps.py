"""Sim time as ROS stamps it: whole seconds and nanoseconds (builtin_interfaces/Time), written once
for the bridge's messages (ros_bridge/worker/messages.py re-exports `stamp_of`), the recorder's log
times and `batchsim resim`'s matching of recorded stamps to re-run periods."""

from __future__ import annotations

import numpy as np

NS = 1_000_000_000


def stamp_of(time: float) -> tuple[int, int]:
    """(sec, nanosec) of a sim time in seconds, nanosec in [0, 1e9)."""
    sec = int(np.floor(time))
    nanosec = int(round((time - sec) * 1e9))
    if nanosec >= NS:
        sec, nanosec = sec + 1, nanosec - NS
    return sec, nanosec


def stamp_ns(time: float) -> int:
    """A sim time as its stamp's whole nanoseconds (an MCAP log time)."""
    sec, nanosec = stamp_of(time)
    return sec * NS + nanosec


def stamps_ns(times: np.ndarray) -> np.ndarray:
    """`stamp_ns` of every time in `times` (int64), with NumPy: the same rounding, half to even."""
    times = np.asarray(times, np.float64)
    sec = np.floor(times)
    return sec.astype(np.int64) * NS + np.round((times - sec) * 1e9).astype(np.int64)


def message_ns(stamp) -> int:
    """A message's builtin_interfaces/Time (`sec`, `nanosec`) as whole nanoseconds."""
    return int(stamp.sec) * NS + int(stamp.nanosec)
