"""Requests a worker hands the loop through its ring, and the services that wait for them.

A request carries a ticket; the loop carries it out between two periods and writes the
last ticket it finished (`svc.done`), whether it succeeded (`svc.ok`) and the sim time
(`svc.time`) back to shared memory; the service answers then, or says the loop did not
answer within SERVICE_WAIT. Services: per world `<ns>/reset`; on worker 0
`/batchsim/{reset,pause,step}`.
"""

from __future__ import annotations

import threading
import time as wallclock
from collections.abc import Callable
from typing import Any

from rclpy.node import Node
from std_srvs.srv import SetBool, Trigger

from batchsim.memory import Memory, Ring
from ros_bridge.naming import topic_name
from ros_bridge.requests import Kind, encode_reset, encode_ticket

SERVICE_WAIT = 2.0  # s a service waits for the loop to carry out its request


class LoopRequests:
    """Worker `index`'s side of the request ring: put a request, wait for the loop to do it.

    `notify()` must be called (by the worker's tick) whenever `svc.done` may have moved.
    """

    def __init__(self, memory: Memory, index: int, ring: Ring, ring_lock: threading.Lock, nudge: Callable[[], None]):
        self.memory = memory
        self.index = index
        self.ring = ring
        self.ring_lock = ring_lock
        self.nudge = nudge
        self.running = True
        self._cond = threading.Condition()

    def put(self, kind: Kind, encode: Callable[[int], bytes]) -> int | None:
        """Queue a request; its ticket, or None when the ring is full (the loop is far behind)."""
        issued = self.memory["svc.issued"]
        with self.ring_lock:
            ticket = int(issued[self.index]) + 1
            if not self.ring.put(kind, encode(ticket)):
                return None
            issued[self.index] = ticket
        self.nudge()
        return ticket

    def wait(self, ticket: int | None, timeout: float = SERVICE_WAIT) -> bool:
        """Whether the loop carried out `ticket` within `timeout` s."""
        if ticket is None:
            return False
        done = self.memory["svc.done"]
        deadline = wallclock.monotonic() + timeout
        with self._cond:
            while int(done[self.index]) < ticket:
                left = deadline - wallclock.monotonic()
                if left <= 0 or not self.running:
                    return False
                self._cond.wait(min(left, 0.05))
        return True

    def ok(self) -> bool:
        """Whether the last request the loop carried out succeeded."""
        return bool(self.memory["svc.ok"][self.index])

    def message(self) -> str:
        """The message the loop gave with its answer to the last request."""
        return self.memory["svc.msg"][self.index].tobytes().rstrip(b"\0").decode(errors="replace")

    def time(self) -> float:
        """The sim time at which the loop carried out the last request."""
        return float(self.memory["svc.time"][self.index])

    def notify(self) -> None:
        with self._cond:
            self._cond.notify_all()


def create_loop_services(node: Node, requests: LoopRequests, namespaces: list[str], lo: int, fleet: bool) -> None:
    """`<ns>/reset` for each world; with `fleet`, `/batchsim/{reset,pause,step}` too."""
    for row, ns in enumerate(namespaces):
        node.create_service(Trigger, topic_name(ns, "reset"), _reset_service(requests, [lo + row], topic_name(ns, "")))
    if not fleet:
        return
    node.create_service(Trigger, "/batchsim/reset", _reset_service(requests, None, "all worlds"))

    def pause(request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        done = requests.wait(requests.put(Kind.PAUSE, lambda t: encode_ticket(t, int(bool(request.data)))))
        response.success = done
        response.message = ("paused" if request.data else "running") if done else "the loop did not answer in time"
        return response

    def step(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        done = requests.wait(requests.put(Kind.STEP, lambda t: encode_ticket(t)))
        ok = done and requests.ok()
        response.success = ok
        if not done:
            response.message = "the loop did not step in time"
        elif not ok:
            response.message = "not paused: /batchsim/step advances one control period while paused"
        else:
            response.message = f"stepped to sim time {requests.time():.6f} s"
        return response

    node.create_service(SetBool, "/batchsim/pause", pause)
    node.create_service(Trigger, "/batchsim/step", step)


def _reset_service(requests: LoopRequests, worlds: list[int] | None, target: str) -> Callable[[Any, Any], Any]:
    def reset(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        done = requests.wait(requests.put(Kind.RESET, lambda t: encode_reset(t, worlds)))
        response.success = True
        response.message = f"reset {target}" if done else f"reset of {target} queued (the loop is busy)"
        return response

    return reset
