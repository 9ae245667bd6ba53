"""A ROS node per controller and per controller_manager of every world, as ros2_control makes them.

ros2_control's controller_manager is a node (`/<ns>/controller_manager`, its parameters
`update_rate` and `<controller>.type`), and every controller it loads is a node of its own,
named after the controller in the manager's namespace (`/<ns>/joint_trajectory_controller`;
`/joint_trajectory_controller` at the root; in a world of several robots, each robot's manager
and controllers in `/<ns>/<robot>`), holding the controller's parameters. Tools find them so:
`ros2 node list`, `ros2 param get /world_3/joint_trajectory_controller joints`, and upstream's
`controller_manager.test_utils.check_controllers_running`, which waits for the controllers'
nodes before it asks `list_controllers`.

A controller's node declares the YAML's parameters and, with their values at start, those
the controller takes at run time (Controller.runtime_parameters: the trajectory controller's
tolerances, gains and `allow_partial_joints_goal`, as upstream's re-reads them). A
`set_parameters` on the node goes to the loop as a SET_PARAMETERS request for the node's world
and is answered with the controller's verdict: set in that world from the next period, or refused
with the reason (a read-only key: change the YAML and restart), the node's value then unchanged.
The controller_manager node's parameters are read-only. The nodes join the worker's executor;
their services are the parameter services only (the manager's `list_controllers`,
`switch_controller`, ... are served by worker/controller_manager.py under the same names). Each
node costs the ROS graph a participant's worth of endpoints to discover (6 services, 2
publishers): BridgeOptions.controller_nodes says for which fleets.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Sequence
from typing import Any

from rcl_interfaces.msg import SetParametersResult
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter

from ros_bridge.manager_link import ManagerSpec
from ros_bridge.protocol.requests import Kind, encode_document
from ros_bridge.worker.services import LoopRequests

READ_ONLY = "the controller_manager's parameters are read-only in batchsim: change the controllers YAML and restart"


def parameter_value(value: Any) -> Any:
    """A YAML value as a ROS parameter value: bool, int, float, str, or a list of one of them;
    anything else (a mixed or nested list, None) as its text."""
    if isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, list | tuple) and value:
        kinds = {type(v) for v in value}
        if len(kinds) == 1 and kinds <= {bool, int, float, str}:
            return list(value)
        if kinds <= {int, float}:
            return [float(v) for v in value]
    return str(value)


def _plain(value: Any) -> Any:
    """A parameter's value as JSON takes it (an array parameter's array.array as a list)."""
    return value if isinstance(value, bool | int | float | str | type(None)) else list(value)


def _valid(key: str) -> bool:
    """A name a ROS parameter may have (a YAML key that is none is left off the node)."""
    return bool(_NAME.fullmatch(key))


_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")


def _namespace(ns: str, prefix: str) -> str:
    parts = [p for p in (ns, prefix.strip("/")) if p]
    return "/" + "/".join(parts)


class ControllerNodes:
    """The nodes of worlds named `namespaces` (ros_bridge/plan.py's), the first being world `lo`
    (a local index, as the loop's requests take it), made in `context`."""

    def __init__(self, context: Context, spec: ManagerSpec, namespaces: Sequence[str], requests: LoopRequests, lo: int):
        self.nodes: list[Node] = []
        self.requests = requests
        for row, ns in enumerate(namespaces):
            for scope in spec.scopes:
                where = _namespace(ns, scope.prefix)
                mine = [spec.controllers[k] for k in scope.controllers]
                manager = [("update_rate", spec.update_rate), *((f"{scope.local(c.name)}.type", c.type) for c in mine)]
                node = self._node("controller_manager", where, context, manager)
                node.add_on_set_parameters_callback(lambda params: SetParametersResult(successful=False, reason=READ_ONLY))
                for c in mine:
                    node = self._node(scope.local(c.name), where, context, [*c.parameters, *c.runtime])
                    node.add_on_set_parameters_callback(functools.partial(self._set, lo + row, c.name, node.get_fully_qualified_name()))

    def _node(self, name: str, namespace: str, context: Context, parameters: Sequence[tuple[str, Any]]) -> Node:
        """A node holding `parameters` (a later value of a key wins)."""
        values = {k: parameter_value(v) for k, v in parameters if _valid(k)}
        node = Node(
            name,
            namespace=namespace,
            context=context,
            parameter_overrides=[Parameter(k, value=v) for k, v in values.items()],
            automatically_declare_parameters_from_overrides=True,
        )
        self.nodes.append(node)
        return node

    def _set(self, world: int, controller: str, where: str, params: list[Parameter]) -> SetParametersResult:
        """A set_parameters on a controller's node: the loop's verdict, as its answer."""
        if not self.requests.admit(world):
            reason, _ = self.requests.refusal(where)
            return SetParametersResult(successful=False, reason=reason)
        values = {p.name: _plain(p.value) for p in params}
        ticket = self.requests.put(
            Kind.SET_PARAMETERS, lambda t: encode_document(t, world, {"controller": controller, "values": values})
        )
        answer = self.requests.wait(ticket)
        if answer is None:
            return SetParametersResult(successful=False, reason="the simulation loop did not answer in time")
        return SetParametersResult(successful=answer.ok, reason=answer.message)

    def close(self) -> None:
        for node in self.nodes:
            node.destroy_node()
        self.nodes.clear()
