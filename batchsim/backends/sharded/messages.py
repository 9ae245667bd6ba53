"""The messages between a fleet and one of its shard processes (batchsim/backends/sharded/shards.py):
both ends of the protocol, side by side.

Each shard has a control row in the fleet's shared memory (`control`, CONTROL int64 per
shard; float fields are float64 views of their slots). One request at a time:

- the fleet writes a request's fields (OP, NSTEP, GIVEN, TIME, PERIOD), then REQUEST + 1;
- the shard writes the reply's fields (PICKLED, LIFECYCLE, BUSY, BEGAN), then REPLY = REQUEST.

Each side writes only its own fields, and its sequence number last; the fleet writes a
request only after the reply to the last. A control period's operations (write and read
with their times, step with its nstep) and their usual answer (nothing: no value, no log
lines, no exception) go through the row alone: nothing is pickled and no socket is read.
Anything else is pickled on the socket pair: a request as (op, args, kwargs), sent after
REQUEST is advanced with OP = PICKLED; a reply as (ok, value, records), sent after REPLY is
advanced with PICKLED set, so that a large message is read while it is written.

Waking: after advancing its sequence number, a side writes one byte to its peer's bell (a
non-blocking pipe). A waiting side polls the sequence number for `spin` seconds, then
sleeps on its bell and the socket (whose end says the peer has gone), and empties the bell
before it looks again: a byte written while it went to sleep wakes it, so none is missed.
Polling saves the wake-up (tens to hundreds of microseconds, four a period). Through the
row, one polled round trip costs the fleet 5-6 us beyond the shard's own work, where the
pickled socket messages cost 23-28 us (one shard on the 2-core VM,
benchmarks/shard_round_trip.py; benchmarks/RESULTS.md, "Four GPUs (issue 27)").
"""

from __future__ import annotations

import logging
import os
import pickle
import select
import threading
import time
from multiprocessing.connection import Connection
from numbers import Real
from typing import Any

import numpy as np

CONTROL = 16  # int64 per shard: two cache lines, the fleet's fields in the first, the shard's in the second
REQUEST, OP, GIVEN, ARGS = 0, 1, 2, 3  # ARGS, ARGS + 1: up to two arguments, int64 or float64
REPLY, PICKLED, LIFECYCLE, BUSY = 8, 9, 10, 11
# float64: time.perf_counter() when the shard began the request. On Linux perf_counter is
# CLOCK_MONOTONIC, one clock for every process, so the fleet can set it beside its own times
# (benchmarks/devices.py: how long a request took to reach the last shard)
BEGAN = 12
PICKLED_OP = -1  # OP of a request that waits on the socket
POLL = 1.0  # s: how often a sleeping side looks at its peer's process
# GIVEN: the argument count in its low two bits, then per argument: given (not None), an integer
_NARGS, _SET, _INT = 3, 4, 16


def control_array(nshard: int) -> tuple[str, tuple[int, ...], str]:
    """The Layout entry of the shards' control rows."""
    return ("control", (nshard, CONTROL), "i8")


class Bell:
    """One direction's wake-up: a non-blocking pipe, rung once per announcement."""

    def __init__(self, read_fd: int, write_fd: int):
        self.read_fd, self.write_fd = read_fd, write_fd
        for fd in (read_fd, write_fd):
            if fd >= 0:
                os.set_blocking(fd, False)

    @classmethod
    def pair(cls) -> Bell:
        return cls(*os.pipe())

    def ring(self) -> None:
        try:
            os.write(self.write_fd, b"\0")
        except BlockingIOError:  # full: the reader has bytes enough to wake it
            pass

    def empty(self) -> None:
        try:
            while os.read(self.read_fd, 65536):
                pass
        except BlockingIOError:
            pass

    def close(self) -> None:
        for fd in (self.read_fd, self.write_fd):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.read_fd = self.write_fd = -1


class _End:
    """What both ends share: the row, the socket, the two bells, the fast operations."""

    def __init__(self, row: np.ndarray, conn: Connection, inbox: Bell, outbox: Bell, ops: tuple, spin: float):
        self.row, self.floats = row, row.view(np.float64)
        self.conn, self.inbox, self.outbox = conn, inbox, outbox
        self.ops, self.spin = ops, float(spin)

    def wait(self, slot: int, value: int, timeout: float) -> bool:
        """Whether row[slot] reaches `value` within `timeout` s; False also as soon as the
        socket is readable without it (the peer gone). Polled for `spin` s, then slept on
        the inbox bell and the socket."""
        row = self.row
        if row[slot] == value:
            return True
        if self.spin > 0:
            deadline = time.perf_counter() + min(self.spin, timeout)
            while time.perf_counter() < deadline:
                if row[slot] == value:
                    return True
        end = time.monotonic() + timeout
        while True:
            self.inbox.empty()
            if row[slot] == value:
                return True
            left = end - time.monotonic()
            if left <= 0:
                return False
            ready, _, _ = select.select([self.inbox.read_fd, self.conn.fileno()], [], [], left)
            if self.conn.fileno() in ready:  # the sequence number is written before the socket
                return bool(row[slot] == value)

    def peer_closed(self) -> bool:
        """Whether the socket is readable with nothing announced: the peer's end is closed."""
        return self.conn.poll(0)

    def close(self) -> None:
        self.inbox.close()
        self.outbox.close()
        self.row = self.floats = np.zeros(CONTROL, np.int64)  # no view left on the fleet's memory


def fast(op: Any, args: tuple, kwargs: dict, ops: tuple) -> bool:
    """Whether a request goes through the control row alone: one of `ops` (the period's:
    write, step, read) with up to two arguments, each a number or None."""
    if op not in ops or kwargs or len(args) > 2:
        return False
    return all(a is None or (isinstance(a, Real) and not isinstance(a, bool)) for a in args)


class FleetEnd(_End):
    """The fleet's end: sends requests, takes replies (inbox: the shard's bell to the fleet)."""

    def send(self, op: Any, args: tuple, kwargs: dict) -> None:
        row = self.row
        if fast(op, args, kwargs, self.ops):
            given = len(args)
            for i, a in enumerate(args):
                if a is None:
                    continue
                given |= _SET << i
                if isinstance(a, int | np.integer):
                    given |= _INT << i
                    row[ARGS + i] = int(a)
                else:
                    self.floats[ARGS + i] = float(a)
            row[OP], row[GIVEN] = self.ops.index(op), given
            row[REQUEST] += 1
            self.outbox.ring()
            return
        row[OP] = PICKLED_OP
        row[REQUEST] += 1
        self.outbox.ring()
        self.conn.send((op, args, kwargs))

    def answered(self, timeout: float) -> bool:
        return self.wait(REPLY, int(self.row[REQUEST]), timeout)

    def began(self) -> float:
        """When the shard began the answered request, by its time.perf_counter() (0.0: not said)."""
        return float(self.floats[BEGAN])

    def reply(self) -> tuple[bool, Any, int, list, float]:
        """The answer (once answered()): (ok, value or exception, lifecycle, log records, busy s)."""
        row = self.row
        lifecycle, busy = int(row[LIFECYCLE]), float(self.floats[BUSY])
        if not row[PICKLED]:
            return True, None, lifecycle, [], busy
        ok, value, records = self.conn.recv()
        return ok, value, lifecycle, records, busy


class ShardEnd(_End):
    """The shard process's end: takes requests, answers them (inbox: the fleet's bell)."""

    def next(self, timeout: float) -> tuple[Any, tuple, dict] | None:
        """The next request as (op, args, kwargs), or None after `timeout` s without one;
        EOFError once the fleet has closed its end."""
        row = self.row
        if not self.wait(REQUEST, int(row[REPLY]) + 1, timeout):
            if self.peer_closed():
                raise EOFError
            return None
        op = int(row[OP])
        if op == PICKLED_OP:
            return self.conn.recv()
        given, args = int(row[GIVEN]), []
        for i in range(given & _NARGS):
            if not given & (_SET << i):
                args.append(None)
            elif given & (_INT << i):
                args.append(int(row[ARGS + i]))
            else:
                args.append(float(self.floats[ARGS + i]))
        return self.ops[op], tuple(args), {}

    def answer(self, ok: bool, value: Any, lifecycle: int, records: list, busy: float, began: float = 0.0) -> None:
        row = self.row
        pickled = not ok or value is not None or bool(records)
        row[PICKLED], row[LIFECYCLE] = int(pickled), lifecycle
        self.floats[BUSY], self.floats[BEGAN] = busy, began
        row[REPLY] = row[REQUEST]
        self.outbox.ring()
        if pickled:
            self.conn.send((ok, value if ok else picklable(value), records))


class Records(logging.Handler):
    """Keeps this process's log records for the next reply."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[tuple[str, int, str]] = []
        self._lock = threading.Lock()

    def emit(self, record: logging.LogRecord) -> None:
        with self._lock:
            self.records.append((record.name, record.levelno, record.getMessage()))

    def take(self) -> list[tuple[str, int, str]]:
        with self._lock:
            out, self.records = self.records, []
        return out


def picklable(e: BaseException) -> BaseException:
    """`e` if it survives pickling, else a RuntimeError with its text."""
    try:
        pickle.loads(pickle.dumps(e))
        return e
    except Exception:
        return RuntimeError(f"{type(e).__name__}: {e}")
