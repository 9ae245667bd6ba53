"""Requests a worker hands the loop through its ring, and the services that wait for them.

A request carries a ticket; the loop carries it out between two periods and writes its
answer (whether it succeeded, a message, the sim time) into shared memory
(ros_bridge/protocol/services.py); the service answers then, or says the loop did not answer
within its wait. Services: per world `<ns>/reset` (and `<ns>/<robot>/reset` per robot of a world of
several); on worker 0 `/batchsim/{reset,pause,step,record}`
(record through its own mailbox, ros_bridge/protocol/recording.py).
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
from ros_bridge.protocol.recording import answer as recorded
from ros_bridge.protocol.recording import next_ticket, put_request
from ros_bridge.protocol.requests import Kind, encode_document, encode_reset, encode_ticket
from ros_bridge.protocol.services import Answer, Tickets

SERVICE_WAIT = 2.0  # s a service waits for the loop to carry out its request
# A service that waits for the loop holds the worker's executor thread a period or so: a flood
# of them on one world held every other world's services behind it (switch_controller p50 6 ms
# -> 555 ms, issue 47). Each world may make WORLD_RATE such requests a second (as many at once);
# beyond, they are refused at once, saying why, and its neighbours' go first. Action goals,
# which wait for nothing but cost the thread their parsing, have a budget of their own.
WORLD_RATE = 20.0
GOAL_RATE = 100.0  # FollowJointTrajectory / GripperCommand goals a second per world


class LoopRequests:
    """Worker `index`'s side of the request ring: put a request, wait for the loop to do it.

    `notify()` must be called (by the worker's tick) whenever `tickets.done()` may have moved.
    """

    def __init__(self, memory: Memory, index: int, ring: Ring, ring_lock: threading.Lock, nudge: Callable[[], None]):
        self.memory = memory
        self.index = index
        self.tickets = Tickets(memory, index)
        self.ring = ring
        self.ring_lock = ring_lock
        self.nudge = nudge
        self.running = True
        self._cond = threading.Condition()
        self._budget: dict[tuple[int, float], tuple[float, float]] = {}  # (world, rate) -> (tokens, when counted)
        self._said: dict[str, float] = {}  # where -> when its refusals were last logged

    def admit(self, world: int, now: float | None = None, rate: float = WORLD_RATE) -> bool:
        """Whether `world` may make one more request of a budget of `rate` a second (a token
        bucket as deep: WORLD_RATE for those that wait for the loop, GOAL_RATE for goals); a
        refused one is answered at once."""
        now = wallclock.monotonic() if now is None else now
        key = (world, rate)
        tokens, then = self._budget.get(key, (rate, now))
        tokens = min(rate, tokens + (now - then) * rate)
        admitted = tokens >= 1.0
        self._budget[key] = (tokens - 1.0 if admitted else tokens, now)
        return admitted

    def refusal(self, where: str, now: float | None = None) -> tuple[str, bool]:
        """A refused request's message, and whether to log it (once in 2 s per `where`)."""
        now = wallclock.monotonic() if now is None else now
        log = now - self._said.get(where, -1e9) >= 2.0
        if log:
            self._said[where] = now
        return (
            f"{where}: more requests a second from this world than its budget (services that wait for the loop: "
            f"{WORLD_RATE:g}, action goals: {GOAL_RATE:g}): refused, so that the other worlds' go first",
            log,
        )

    def put(self, kind: Kind, encode: Callable[[int], bytes]) -> int | None:
        """Queue a request; its ticket, or None when the ring is full (the loop is far behind)."""
        with self.ring_lock:
            ticket = self.tickets.next()
            if not self.ring.put(kind, encode(ticket)):
                return None
            self.tickets.issued(ticket)
        self.nudge()
        return ticket

    def wait(self, ticket: int | None, timeout: float = SERVICE_WAIT) -> Answer | None:
        """The loop's answer to `ticket`, or None if it gave none within `timeout` s."""
        if ticket is None:
            return None
        deadline = wallclock.monotonic() + timeout
        with self._cond:
            while (answer := self.tickets.answer(ticket)) is None:
                left = deadline - wallclock.monotonic()
                if left <= 0 or not self.running:
                    return None
                self._cond.wait(min(left, 0.05))
        return answer

    def notify(self) -> None:
        with self._cond:
            self._cond.notify_all()


def create_loop_services(
    node: Node, requests: LoopRequests, namespaces: list[str], lo: int, fleet: bool, robots: tuple[str, ...] = ()
) -> None:
    """`<ns>/reset` for each world, and `<ns>/<robot>/reset` for each robot of a world of several;
    with `fleet`, `/batchsim/{reset,pause,step}` too."""
    for row, ns in enumerate(namespaces):
        node.create_service(Trigger, topic_name(ns, "reset"), _reset_service(requests, [lo + row], topic_name(ns, "")))
        for k, robot in enumerate(robots):
            node.create_service(Trigger, topic_name(ns, f"{robot}/reset"), _robot_reset_service(requests, lo + row, k))
    if not fleet:
        return
    node.create_service(Trigger, "/batchsim/reset", _reset_service(requests, None, "all worlds"))

    def pause(request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        answer = requests.wait(requests.put(Kind.PAUSE, lambda t: encode_ticket(t, int(bool(request.data)))))
        response.success = answer is not None
        response.message = ("paused" if request.data else "running") if answer else "the loop did not answer in time"
        return response

    def step(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        answer = requests.wait(requests.put(Kind.STEP, lambda t: encode_ticket(t)))
        response.success = answer is not None and answer.ok
        if answer is None:
            response.message = "the loop did not step in time"
        elif not answer.ok:
            response.message = "not paused: /batchsim/step advances one control period while paused"
        else:
            response.message = f"stepped to sim time {answer.time:.6f} s"
        return response

    node.create_service(SetBool, "/batchsim/pause", pause)
    node.create_service(Trigger, "/batchsim/step", step)
    if "rec.req" in requests.memory:
        node.create_service(SetBool, "/batchsim/record", _record_service(requests))


def _robot_reset_service(requests: LoopRequests, world: int, robot: int) -> Callable[..., Any]:
    """`<ns>/<robot>/reset`: that robot of that world back where it starts, the others as they are."""

    def reset(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if not requests.admit(world):  # one world's flood
            response.success, response.message = False, requests.refusal(f"world {world}'s robot reset")[0]
            return response
        answer = requests.wait(requests.put(Kind.RESET_ROBOT, lambda t: encode_document(t, world, {"robot": robot})))
        response.success = answer is not None and answer.ok
        response.message = "the loop did not answer in time" if answer is None else answer.message
        return response

    return reset


def _record_service(requests: LoopRequests) -> Callable[[Any, Any], Any]:
    """`/batchsim/record`: true starts an MCAP recording (ros_bridge/recording.py), false stops it."""
    memory = requests.memory

    def record(request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        ticket = next_ticket(memory)
        put_request(memory, ticket, bool(request.data))
        deadline = wallclock.monotonic() + SERVICE_WAIT
        while (answer := recorded(memory, ticket)) is None and wallclock.monotonic() < deadline:
            wallclock.sleep(0.01)
        late = (False, "the loop did not answer in time (starting or busy): nothing was started or stopped")
        response.success, response.message = answer if answer is not None else late
        return response

    return record


def _reset_service(requests: LoopRequests, worlds: list[int] | None, target: str) -> Callable[[Any, Any], Any]:
    def reset(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if worlds is not None and not requests.admit(worlds[0]):  # one world's flood
            response.success, response.message = False, requests.refusal(target)[0]
            return response
        done = requests.wait(requests.put(Kind.RESET, lambda t: encode_reset(t, worlds))) is not None
        response.success = True
        response.message = f"reset {target}" if done else f"reset of {target} queued (the loop is busy)"
        return response

    return reset
