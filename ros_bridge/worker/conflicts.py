"""At start, with `--check`: is another process already serving this worker's worlds or /clock?"""

from __future__ import annotations

import os
import time as wallclock

from rclpy.node import Node

from ros_bridge.naming import topic_name
from ros_bridge.plan import FleetPlan


def check_conflicts(node: Node, plan: FleetPlan, index: int) -> tuple[str, str] | None:
    """Watch the graph for `plan.startup_check` s: another process that serves one of
    the plan's namespaces, or a /clock publisher when this process would publish one too.
    Returns (kind, message) with kind "namespace" or "clock", or None."""
    if os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").upper() in ("LOCALHOST", "OFF"):
        return None  # no other host can join: the host's registry (registry.py) has seen every fleet
    mine = {topic_name(ns, "reset") for ns in plan.namespaces}
    own = plan.node_names[index]
    deadline = wallclock.monotonic() + plan.startup_check
    extended = False
    while True:
        unresolved = False
        names = node.get_node_names_and_namespaces()
        seen_own = False
        for name, ns in names:
            if not name.startswith("batchsim"):
                continue
            if name == own and ns == "/" and not seen_own:
                seen_own = True  # this node; another of the same name is another process's
                continue
            services = [s for s, _ in node.get_service_names_and_types_by_node(name, ns)]
            if not any(s.endswith("/reset") for s in services):
                unresolved = True  # the node is known, its worlds' services not yet
                continue
            clash = sorted(s for s in services if s in mine)
            if clash:
                where = clash[0].rsplit("/", 1)[0]
                more = f" and {len(clash) - 1} more" if len(clash) > 1 else ""
                return (
                    "namespace",
                    f"another batchsim process already serves {where}{more} (node {_full(ns, name)}): "
                    "give this one other worlds (a world offset or another namespace template) or another "
                    "ROS domain (a process killed outright stays in the ROS graph for up to 20 s)",
                )
        if plan.clock:
            for info in node.get_publishers_info_by_topic("/clock"):
                return (
                    "clock",
                    f"another process already publishes /clock (node {_full(info.node_namespace, info.node_name)}): "
                    "only one process of a fleet may",
                )
        now = wallclock.monotonic()
        if now >= deadline:
            if unresolved and not extended:
                deadline, extended = now + 4.0, True
                continue
            return None
        wallclock.sleep(0.1)


def _full(namespace: str, name: str) -> str:
    return f"{namespace.rstrip('/')}/{name}"
