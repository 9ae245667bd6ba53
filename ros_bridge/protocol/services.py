"""The service answers: how the loop answers the requests a worker put in its ring (a reset,
a pause, a step, a switch, ...). Its writer (the physics process, `put_answer`) and its
reader (a worker, `Tickets`) are both here, with their arrays; no rclpy.

A worker numbers its requests (`svc.issued`, its last ticket); the loop carries a request out
between two periods and writes its answer (whether it succeeded, a message, the sim time)
into the worker's slot ticket % SERVICE_SLOTS, the slot's ticket written last, then moves
`svc.done` (the newest ticket carried out), which a worker's tick watches to wake the
services waiting for an answer. Several requests may wait at once (a step_simulation while a
set_pause is answered): up to SERVICE_SLOTS per worker.
"""

from __future__ import annotations

import dataclasses

from batchsim.memory import Memory
from ros_bridge.protocol.text import put_text, text_of

SERVICE_MESSAGE = 1024  # bytes of a service answer's message the loop hands back
SERVICE_SLOTS = 16  # answers kept per worker: at most this many of its requests may wait at once


def service_arrays(nworker: int) -> list[tuple[str, tuple[int, ...], str]]:
    """The shared arrays of `nworker` workers' requests and answers."""
    return [
        ("svc.issued", (nworker,), "i8"),  # per worker: its last ticket
        ("svc.done", (nworker,), "i8"),  # per worker: the newest ticket the loop carried out
        ("svc.ticket", (nworker, SERVICE_SLOTS), "i8"),  # the ticket a slot answers, written last
        ("svc.time", (nworker, SERVICE_SLOTS), "f8"),  # the sim time when the loop carried it out
        ("svc.ok", (nworker, SERVICE_SLOTS), "i8"),  # 1 when it succeeded
        ("svc.msg", (nworker, SERVICE_SLOTS, SERVICE_MESSAGE), "u1"),  # the message, utf-8, NUL-padded
    ]


@dataclasses.dataclass(frozen=True)
class Answer:
    """The loop's answer to one request."""

    ok: bool
    message: str
    time: float  # the sim time at which the loop carried it out


def put_answer(memory: Memory, worker: int, ticket: int, time: float, ok: bool, message: str = "") -> None:
    """The loop: `worker`'s request `ticket` is carried out (its slot, the ticket written last)."""
    slot = ticket % SERVICE_SLOTS
    memory["svc.ok"][worker, slot] = int(ok)
    put_text(memory["svc.msg"][worker, slot], message)
    memory["svc.time"][worker, slot] = time
    memory["svc.ticket"][worker, slot] = ticket
    memory["svc.done"][worker] = max(int(memory["svc.done"][worker]), ticket)


class Tickets:
    """Worker `worker`'s side: its tickets, and the loop's answers to them."""

    def __init__(self, memory: Memory, worker: int):
        self.worker = worker
        self._issued = memory["svc.issued"]
        self._done = memory["svc.done"]
        self._ticket = memory["svc.ticket"][worker]
        self._time = memory["svc.time"][worker]
        self._ok = memory["svc.ok"][worker]
        self._msg = memory["svc.msg"][worker]

    def next(self) -> int:
        """The ticket of the next request (`issued` once it is in the ring)."""
        return int(self._issued[self.worker]) + 1

    def issued(self, ticket: int) -> None:
        self._issued[self.worker] = ticket

    def done(self) -> int:
        """The newest ticket the loop carried out."""
        return int(self._done[self.worker])

    def answer(self, ticket: int) -> Answer | None:
        """The loop's answer to `ticket` if it has given it."""
        slot = ticket % SERVICE_SLOTS
        if int(self._ticket[slot]) != ticket:
            return None
        return Answer(bool(self._ok[slot]), text_of(self._msg[slot]), float(self._time[slot]))
