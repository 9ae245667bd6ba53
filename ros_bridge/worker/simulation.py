"""mujoco_ros2_control's simulation services (mujoco_ros2_control_msgs), served for a fleet.

Fleet-wide, on a node of their own named `mujoco_ros2_control_node` (worker 0, from the
start), as mujoco_ros2_control serves its `~/...` services:

    /mujoco_ros2_control_node/reset_world      every world (with one world, that one)
    /mujoco_ros2_control_node/set_pause        the whole fleet (its worlds run in lockstep)
    /mujoco_ros2_control_node/step_simulation  N physics steps of every world while paused;
                                               0 refused; a resume ends it not ok

Per world, created when a client appears (on_request.py):
`/<ns>/mujoco_ros2_control_node/{reset_world, set_free_joint_state}`. With one world in the
root namespace both sets are one. With the ExternalWrenchPlugin, `/<ns>/<plugin>/apply_wrench`
too (ros_bridge/worker/wrench.py), on the fleet node (worker 0) or on a node of the worker's
own, `/<worker's node>/mujoco_ros2_control_node`, spun the same way.

The fleet node spins its own multi-threaded executor: a step_simulation waits for the loop
(up to max(30 s, 10 ms per step), as upstream) while a set_pause must still be answered,
which mujoco_ros2_control does with a callback group per service. The requests go to the
loop through the worker's ring (services.py); ros_bridge/simulation.py carries them out.
"""

from __future__ import annotations

import threading
from typing import Any

from mujoco_ros2_control_msgs.srv import ResetWorld, SetFreeJointState, SetPause, StepSimulation
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node

from ros_bridge.naming import topic_name
from ros_bridge.plan import FleetPlan
from ros_bridge.protocol.requests import Kind, encode_document, encode_ticket
from ros_bridge.worker.on_request import OnRequest
from ros_bridge.worker.services import SERVICE_WAIT, LoopRequests

NODE = "mujoco_ros2_control_node"
STEP_WAIT_MIN = 30.0  # s a step_simulation waits at least, and 10 ms per step beyond (upstream's)


def free_joints(entries: Any) -> list[dict]:
    """FreeJointState[] as plain data (an unset orientation is the identity, as upstream)."""
    out = []
    for e in entries:
        p, q = e.pose.pose.position, e.pose.pose.orientation
        quat = [q.w, q.x, q.y, q.z]
        if not any(quat):
            quat = [1.0, 0.0, 0.0, 0.0]
        t = e.twist.twist
        out.append(
            {
                "name": e.name,
                "pose": [p.x, p.y, p.z, *quat],
                "pose_frame": e.pose.header.frame_id,
                "twist": [t.linear.x, t.linear.y, t.linear.z, t.angular.x, t.angular.y, t.angular.z],
                "twist_frame": e.twist.header.frame_id,
            }
        )
    return out


class SimulationServices(OnRequest):
    """The services of worker `index`'s worlds; worker 0 also serves the fleet's."""

    def __init__(self, node: Node, requests: LoopRequests, plan: FleetPlan, index: int):
        super().__init__()
        self.node = node
        self.requests = requests
        self._entities: list[Any] = []
        self._side_node: Node | None = None  # the fleet node, or the wrench services' node
        self._executor: MultiThreadedExecutor | None = None
        self._thread: threading.Thread | None = None
        self.wrench: Any = None  # the ExternalWrenchPlugin's apply_wrench (ros_bridge/worker/wrench.py)
        lo, hi = plan.ranges[index]
        fleet = index == 0
        root = topic_name("", NODE)
        for row, ns in enumerate(plan.namespaces[lo:hi]):
            base = topic_name(ns, NODE)
            if base == root:  # the root-namespace world: its services are the fleet node's
                if fleet:
                    self._world_services(node, base, lo + row, reset=False)
            else:
                self.offer(base, lo + row)
        if fleet or plan.wrench_service:
            self._start_side_node(node, fleet, "" if fleet else f"/{plan.node_names[index]}")
        if plan.wrench_service:
            from ros_bridge.worker.wrench import WrenchServices

            self.wrench = WrenchServices(self._side_node, requests, plan.namespaces[lo:hi], lo, plan.wrench_service)

    def requested(self, name: str) -> bool:
        return super().requested(name) or (self.wrench is not None and self.wrench.requested(name))

    def create_all(self) -> None:
        super().create_all()
        if self.wrench is not None:
            self.wrench.create_all()

    def _create(self, base: str, world: int) -> None:
        self._world_services(self.node, base, world, reset=True)

    def _world_services(self, node: Node, base: str, world: int, *, reset: bool) -> None:
        if reset:
            self._entities.append(node.create_service(ResetWorld, f"{base}/reset_world", self._reset(world)))
        self._entities.append(node.create_service(SetFreeJointState, f"{base}/set_free_joint_state", self._set_free(world)))

    def _start_side_node(self, node: Node, fleet: bool, namespace: str) -> None:
        """A `mujoco_ros2_control_node` on its own multi-threaded executor: the fleet's services
        (worker 0's, at the root), and the wrench services (another worker's, in `namespace`)."""
        side = Node(NODE, namespace=namespace, context=node.context)
        if fleet:
            group = ReentrantCallbackGroup()
            base = topic_name("", NODE)
            for srv, name, handler in (
                (ResetWorld, "reset_world", self._reset(-1)),
                (SetPause, "set_pause", self._set_pause),
                (StepSimulation, "step_simulation", self._step),
            ):
                self._entities.append(side.create_service(srv, f"{base}/{name}", handler, callback_group=group))
        self._side_node = side
        self._executor = MultiThreadedExecutor(num_threads=4, context=node.context)
        self._executor.add_node(side)
        self._thread = threading.Thread(target=self._spin, name="mujoco_ros2_control_node", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        executor = self._executor
        while executor is not None and self.requests.running and self.node.context.ok():
            wrench = self.wrench
            try:
                # a waiting apply_wrench is resumed every cycle: cycles of 20 ms while one waits
                executor.spin_once(timeout_sec=0.02 if wrench is not None and wrench.busy else 0.1)
                if wrench is not None:
                    wrench.drain()  # its services are created on this node's thread
            except Exception:  # shutting down
                if not self.requests.running or not self.node.context.ok():
                    break

    def close(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(timeout_sec=1.0)
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._side_node is not None:
            self._side_node.destroy_node()

    # --- handlers ---
    def _answer(self, response: Any, ticket: int | None, timeout: float = SERVICE_WAIT) -> Any:
        answer = self.requests.wait(ticket, timeout)
        if answer is None:
            response.success = False
            response.message = "the simulation loop did not answer in time" if ticket else "the loop is too far behind"
        else:
            response.success, response.message = answer.ok, answer.message
        return response

    def _reset(self, world: int) -> Any:
        def reset(request: Any, response: Any) -> Any:
            js = request.state_overrides.joint_states
            document = {
                "keyframe": request.keyframe,
                "joints": {
                    "name": list(js.name),
                    "position": [float(v) for v in js.position],
                    "velocity": [float(v) for v in js.velocity],
                    "effort": [float(v) for v in js.effort],
                },
                "free": free_joints(request.state_overrides.free_joints),
            }
            return self._answer(response, self.requests.put(Kind.RESET_WORLD, lambda t: encode_document(t, world, document)))

        return reset

    def _set_free(self, world: int) -> Any:
        def set_free(request: Any, response: Any) -> Any:
            document = {"free": free_joints(request.free_joints)}
            return self._answer(
                response, self.requests.put(Kind.SET_FREE_JOINTS, lambda t: encode_document(t, world, document))
            )

        return set_free

    def _set_pause(self, request: Any, response: Any) -> Any:
        return self._answer(response, self.requests.put(Kind.PAUSE, lambda t: encode_ticket(t, int(bool(request.paused)))))

    def _step(self, request: Any, response: Any) -> Any:
        steps = int(request.steps)
        if steps == 0:
            response.success = False
            response.message = "Number of steps must be positive, got: 0"
            return response
        wait = max(STEP_WAIT_MIN, 0.01 * steps)
        answer = self.requests.wait(self.requests.put(Kind.STEP_N, lambda t: encode_ticket(t, steps)), wait)
        if answer is None:
            response.success = False
            response.message = f"Timeout waiting for {steps} simulation step(s)."
        else:
            response.success, response.message = answer.ok, answer.message
        return response
