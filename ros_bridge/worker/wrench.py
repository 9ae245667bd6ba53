"""mujoco_ros2_control's ExternalWrenchPlugin service, for a worker's worlds.

Upstream's plugin creates `apply_wrench` (mujoco_ros2_control_msgs/ApplyExternalWrench) on
`create_sub_node(<plugin name>)` of the `mujoco_ros2_control_node`; rclcpp puts a sub-node's
relative names under `<node's namespace>/<plugin name>/` (not under the node's name, as `~/`
would), so one robot in the root namespace serves `/<plugin name>/apply_wrench`, and world
`<ns>` here serves `/<ns>/<plugin name>/apply_wrench`. Each world's is created when a client of
it appears (on_request.py).

A request is checked whole by the loop (ros_bridge/simulation.py, batchsim.plugins.external_wrench),
answered at once when it is refused (upstream's words: "Body 'x' not found in MuJoCo model."),
and otherwise when its longest wrench has run: upstream's callback sleeps that long in wall
time; here the wait is in sim time, whatever the real-time factor, until the loop marks the
request done (ros_bridge/protocol/requests.py). An empty request is answered at once, as upstream's.
Upstream's `~/wrench_markers` (visualization_msgs/MarkerArray) is not published.

The handlers are coroutines on a node spun by rclpy's standard executor (the worker's own node
spins an EventsExecutor, whose services cannot answer later): a request waiting for its wrench
holds no thread, and the executor comes back to it every cycle (SimulationServices' spin loop).
"""

from __future__ import annotations

import threading
import time as wallclock
from typing import Any

from mujoco_ros2_control_msgs.srv import ApplyExternalWrench
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node

from ros_bridge.naming import topic_name
from ros_bridge.protocol.requests import Kind, encode_document, wrench_done
from ros_bridge.worker.messages import seconds
from ros_bridge.worker.on_request import OnRequest
from ros_bridge.worker.services import SERVICE_WAIT, LoopRequests

EMPTY = "No wrenches provided; nothing applied."  # upstream's words


class _NextCycle:
    """Awaited in a service's coroutine: back to the executor, which resumes it next cycle."""

    def __await__(self):
        yield


def wrench_entries(request: Any) -> list[dict]:
    """ExternalWrench[] as plain data (batchsim.plugins.external_wrench.ExternalWrench's fields)."""
    out = []
    for e in request.wrenches.external_wrenches:
        f, t, p = e.wrench.wrench.force, e.wrench.wrench.torque, e.application_point
        out.append(
            {
                "body": e.wrench.header.frame_id,
                "force": [f.x, f.y, f.z],
                "torque": [t.x, t.y, t.z],
                "point": [p.x, p.y, p.z],
                "duration": seconds(e.duration),
                "ramp_down": seconds(e.ramp_down_duration),
            }
        )
    return out


class WrenchServices(OnRequest):
    """`<ns>/<service>` of worlds [lo, lo + len(namespaces)), on `node` (spun by a standard
    executor, whose thread calls `drain()`; `busy` while a request waits)."""

    def __init__(self, node: Node, requests: LoopRequests, namespaces: list[str], lo: int, service: str):
        super().__init__()
        self.node = node
        self.requests = requests
        self._group = ReentrantCallbackGroup()
        self._waiting = 0
        self._lock = threading.Lock()
        self._services: list[Any] = []
        for row, ns in enumerate(namespaces):
            self.offer(topic_name(ns, service), lo + row)

    def base_of(self, name: str) -> str | None:
        return name  # one service per key

    def create_all(self) -> None:
        """`--all-topics`: every world's, created on the node's own thread (drain) all the same."""
        self._to_create.extend(self._pending.items())
        self._pending.clear()

    @property
    def busy(self) -> bool:
        """A request waits, or services are to be created: the spin loop should come back soon."""
        return self._waiting > 0 or self.pending

    def _create(self, name: str, world: int) -> None:
        self._services.append(
            self.node.create_service(ApplyExternalWrench, name, self._handler(name, world), callback_group=self._group)
        )

    def _handler(self, name: str, world: int) -> Any:
        async def apply(request: Any, response: Any) -> Any:
            entries = wrench_entries(request)
            if not entries:
                response.success, response.message = True, EMPTY
                return response
            with self._lock:
                self._waiting += 1
            try:
                response.success, response.message = await self._carry_out(name, world, {"wrenches": entries})
            finally:
                with self._lock:
                    self._waiting -= 1
            return response

        return apply

    async def _carry_out(self, name: str, world: int, document: dict) -> tuple[bool, str]:
        requests = self.requests
        ticket = requests.put(Kind.APPLY_WRENCH, lambda t: encode_document(t, world, document))
        if ticket is None:
            return False, "the loop is too far behind"
        deadline = wallclock.monotonic() + SERVICE_WAIT
        while (answer := requests.tickets.answer(ticket)) is None:
            if wallclock.monotonic() > deadline or not requests.running:
                return False, "the simulation loop did not answer in time"
            await _NextCycle()
        if not answer.ok:
            self.node.get_logger().warning(f"{name}: {answer.message}")
            return False, answer.message
        while not wrench_done(requests.memory, requests.index, ticket):  # as long as the sim time takes
            if not requests.running:
                return False, "the simulation stopped before the wrenches had run"
            await _NextCycle()
        return True, answer.message
