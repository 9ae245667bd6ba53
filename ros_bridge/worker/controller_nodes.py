"""A ROS node per controller and per controller_manager of every world, as ros2_control makes them.

ros2_control's controller_manager is a node (`/<ns>/controller_manager`, its parameters
`update_rate` and `<controller>.type`), and every controller it loads is a node of its own,
named after the controller in the manager's namespace (`/<ns>/joint_trajectory_controller`;
`/joint_trajectory_controller` at the root; in a world of several robots, each robot's manager
and controllers in `/<ns>/<robot>`), holding the controller's parameters. Tools find them so:
`ros2 node list`, `ros2 param get /world_3/joint_trajectory_controller joints`, and upstream's
`controller_manager.test_utils.check_controllers_running`, which waits for the controllers'
nodes before it asks `list_controllers`.

The parameters are read-only here: batchsim's controllers take theirs when the fleet starts, so
a `set_parameters` request is refused with a reason (change the YAML and restart). The nodes
join the worker's executor; their services are the parameter services only (the manager's
`list_controllers`, `switch_controller`, ... are served by worker/controller_manager.py under
the same names). Each node costs the ROS graph a participant's worth of endpoints to discover
(6 services, 2 publishers): BridgeOptions.controller_nodes says for which fleets.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Any

from rcl_interfaces.msg import SetParametersResult
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter

from ros_bridge.manager_link import ManagerSpec

READ_ONLY = "batchsim's controllers take their parameters at start: change the controllers YAML and restart"


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


def _valid(key: str) -> bool:
    """A name a ROS parameter may have (a YAML key that is none is left off the node)."""
    return bool(_NAME.fullmatch(key))


_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")


def _namespace(ns: str, prefix: str) -> str:
    parts = [p for p in (ns, prefix.strip("/")) if p]
    return "/" + "/".join(parts)


class ControllerNodes:
    """The nodes of worlds named `namespaces` (ros_bridge/plan.py's), made in `context`."""

    def __init__(self, context: Context, spec: ManagerSpec, namespaces: Sequence[str]):
        self.nodes: list[Node] = []
        for ns in namespaces:
            for scope in spec.scopes:
                where = _namespace(ns, scope.prefix)
                mine = [spec.controllers[k] for k in scope.controllers]
                manager = [("update_rate", spec.update_rate), *((f"{scope.local(c.name)}.type", c.type) for c in mine)]
                self._node("controller_manager", where, context, manager)
                for c in mine:
                    self._node(scope.local(c.name), where, context, c.parameters)

    def _node(self, name: str, namespace: str, context: Context, parameters: Sequence[tuple[str, Any]]) -> None:
        node = Node(
            name,
            namespace=namespace,
            context=context,
            parameter_overrides=[Parameter(k, value=parameter_value(v)) for k, v in parameters if _valid(k)],
            automatically_declare_parameters_from_overrides=True,
        )
        node.add_on_set_parameters_callback(lambda params: SetParametersResult(successful=False, reason=READ_ONLY))
        self.nodes.append(node)

    def close(self) -> None:
        for node in self.nodes:
            node.destroy_node()
        self.nodes.clear()
