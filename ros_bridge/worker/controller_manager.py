"""Every world's controller_manager services, as ros2_control's controller_manager serves them.

Under `/<ns>/controller_manager/` for each world of the worker (what `ros2 control ...
-c /<ns>/controller_manager` and MoveIt's ros2_control controller manager plugin call); in a
world of several robots, under `/<ns>/<robot>/controller_manager/` for each robot, showing and
switching only its controllers, by the names its own YAML gives them (ManagerScope):

- list_controllers, list_hardware_interfaces, list_hardware_components,
  list_controller_types: answered here, from the plan (ManagerSpec) and the per-world
  active masks the loop keeps in shared memory (ros_bridge/protocol/active.py);
- switch_controller: handed to the loop as a SWITCH request (ros_bridge/manager_link.py);
  the answer (ros2_control's `ok` and `message`) waits until the loop carried it out;
Each world's services are created when a client of one of them appears in the ROS graph
(scanned every second), or all at start with `--all-topics`.

- load_controller / configure_controller: every controller of the YAML is loaded and
  configured at start, so these answer `ok` for a controller that exists (a spawner run
  against the fleet goes on to switch it) and not for others; unload_controller and
  reload_controller_libraries answer not ok (batchsim does not load plugins at run time).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from controller_manager_msgs.msg import ControllerState, HardwareComponentState, HardwareInterface
from controller_manager_msgs.srv import (
    ConfigureController,
    ListControllers,
    ListControllerTypes,
    ListHardwareComponents,
    ListHardwareInterfaces,
    LoadController,
    ReloadControllerLibraries,
    SwitchController,
    UnloadController,
)
from lifecycle_msgs.msg import State
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from batchsim.memory import Memory
from ros_bridge.manager_link import ManagerScope, ManagerSpec
from ros_bridge.naming import topic_name
from ros_bridge.protocol.active import ActiveReader
from ros_bridge.protocol.requests import Kind, encode_switch
from ros_bridge.worker.on_request import OnRequest
from ros_bridge.worker.services import LoopRequests

# the requests a service holds before it takes them: ROS's default (10) lost all but 11 of a burst
# of 5,000 list_controllers calls, where upstream's controller_manager answers every one
SERVICE_QOS = QoSProfile(depth=10_000, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)


class ControllerManagerServices(OnRequest):
    """The services of worlds [lo, lo + len(namespaces)) (local indices)."""

    def __init__(self, node: Node, spec: ManagerSpec, memory: Memory, requests: LoopRequests, namespaces: list[str], lo: int):
        super().__init__()
        self.spec = spec
        self.active = ActiveReader(memory)
        self.requests = requests
        self.logger = node.get_logger()
        self._services: list[Any] = []
        self._node = node
        # per world and robot, created when a client of one of its services appears (on_request.py):
        # nine services a world in a fleet of thousands would cost discovery time for nothing
        for row, ns in enumerate(namespaces):
            for scope in spec.scopes:
                self.offer(topic_name(ns, f"{scope.prefix}controller_manager"), (lo + row, scope))

    def _create(self, base: str, value: tuple[int, ManagerScope]) -> None:
        for srv, name, handler in (
            (ListControllers, "list_controllers", self._list_controllers),
            (ListHardwareInterfaces, "list_hardware_interfaces", self._list_hardware_interfaces),
            (ListHardwareComponents, "list_hardware_components", self._list_hardware_components),
            (ListControllerTypes, "list_controller_types", self._list_controller_types),
            (SwitchController, "switch_controller", self._switch_controller),
            (LoadController, "load_controller", self._exists),
            (ConfigureController, "configure_controller", self._exists),
            (UnloadController, "unload_controller", self._refuse),
            (ReloadControllerLibraries, "reload_controller_libraries", self._refuse),
        ):
            self._services.append(
                self._node.create_service(srv, f"{base}/{name}", _bind(handler, value, f"{base}/{name}"), qos_profile=SERVICE_QOS)
            )

    def _claimed(self, world: int) -> dict[str, str]:
        """command interface -> the controller active in `world` that claims it (world names)."""
        active = self.active.row(world)
        return {i: c.name for k, c in enumerate(self.spec.controllers) if active[k] for i in c.command_interfaces}

    def _list_controllers(self, at: tuple[int, ManagerScope], where: str, request: Any, response: Any) -> Any:
        world, scope = at
        active = self.active.row(world)
        local = scope.local
        for k in scope.controllers:
            c, on = self.spec.controllers[k], bool(active[k])
            response.controller.append(
                ControllerState(
                    name=local(c.name),
                    state="active" if on else "inactive",
                    type=c.type,
                    is_async=False,
                    update_rate=min(max(c.update_rate, 0), 65535),
                    claimed_interfaces=[local(i) for i in c.command_interfaces] if on else [],
                    required_command_interfaces=[local(i) for i in c.command_interfaces],
                    required_state_interfaces=[local(i) for i in c.state_interfaces],
                    is_chainable=False,
                    is_chained=False,
                )
            )
        return response

    def _interfaces(self, at: tuple[int, ManagerScope]) -> tuple[list[HardwareInterface], list[HardwareInterface]]:
        world, scope = at
        claimed = self._claimed(world)
        command = [
            HardwareInterface(name=scope.local(n), data_type="double", is_available=True, is_claimed=n in claimed)
            for n in scope.command_interfaces
        ]
        state = [
            HardwareInterface(name=scope.local(n), data_type="double", is_available=True, is_claimed=False)
            for n in scope.state_interfaces
        ]
        return command, state

    def _list_hardware_interfaces(self, at: tuple[int, ManagerScope], where: str, request: Any, response: Any) -> Any:
        response.command_interfaces, response.state_interfaces = self._interfaces(at)
        return response

    def _list_hardware_components(self, at: tuple[int, ManagerScope], where: str, request: Any, response: Any) -> Any:
        command, state = self._interfaces(at)
        response.component.append(
            HardwareComponentState(
                name=at[1].hardware,
                type="system",
                is_async=False,
                plugin_name="batchsim/BatchedSystem",
                state=State(id=State.PRIMARY_STATE_ACTIVE, label="active"),
                command_interfaces=command,
                state_interfaces=state,
            )
        )
        return response

    def _list_controller_types(self, at: tuple[int, ManagerScope], where: str, request: Any, response: Any) -> Any:
        response.types = [t for t, _ in self.spec.types]
        response.base_classes = [b for _, b in self.spec.types]
        return response

    def _switch_controller(self, at: tuple[int, ManagerScope], where: str, request: Any, response: Any) -> Any:
        world, scope = at
        if not self.requests.admit(world):  # a flood from this world waits behind nobody's
            response.ok = False
            response.message, log = self.requests.refusal(where)
            if log:
                self.logger.warning(response.message)
            return response
        # a robot's names become the world's: its own controllers only (another robot's name is unknown here)
        activate = [scope.prefix + n for n in request.activate_controllers]
        deactivate = [scope.prefix + n for n in request.deactivate_controllers]
        strictness = int(request.strictness)
        ticket = self.requests.put(
            Kind.SWITCH, lambda t: encode_switch(t, world, activate, deactivate, strictness, bool(request.activate_asap))
        )
        answer = self.requests.wait(ticket)
        if answer is None:
            response.ok = False
            response.message = "the simulation loop did not carry out the switch in time"
        else:
            response.ok, response.message = answer.ok, answer.message.replace(scope.prefix, "") if scope.prefix else answer.message
        if not response.ok:
            self.logger.warning(f"{where}: switch refused: {response.message}")
        return response

    def _exists(self, at: tuple[int, ManagerScope], where: str, request: Any, response: Any) -> Any:
        scope = at[1]
        known = {scope.local(self.spec.controllers[k].name) for k in scope.controllers}
        response.ok = request.name in known
        if not response.ok:
            names = ", ".join(sorted(known)) or "none"
            self.logger.warning(f"{where}: no controller named {request.name!r} (batchsim loads the YAML's: {names})")
        return response

    def _refuse(self, at: tuple[int, ManagerScope], where: str, request: Any, response: Any) -> Any:
        response.ok = False
        self.logger.warning(f"{where}: not supported: batchsim loads its controllers from the YAML at start")
        return response


def _bind(handler: Callable[..., Any], at: tuple[int, ManagerScope], where: str) -> Callable[[Any, Any], Any]:
    return lambda request, response: handler(at, where, request, response)
