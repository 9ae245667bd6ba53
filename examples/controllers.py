"""The `ros2 control` and `ros2 action` recipes of the README, in rclpy (the pip install has no
`ros2` CLI): list a world's controllers, switch one, send a FollowJointTrajectory goal, read and
set a controller's parameter.

    python examples/controllers.py list --world 5
    python examples/controllers.py switch --world 5 --deactivate joint_trajectory_controller
    python examples/controllers.py switch --world 5 --activate joint_trajectory_controller
    python examples/controllers.py goal --world 3 --positions 0.4,-0.3,0.5,0.2,-0.4,0.6 --seconds 1
    python examples/controllers.py param --world 3 --name constraints.goal_time
    python examples/controllers.py param --world 3 --name constraints.goal_time --value 0.5

As `ros2 control list_controllers -c /world_5/controller_manager`, `ros2 control
switch_controllers ... --deactivate ...` and `ros2 action send_goal
/world_3/joint_trajectory_controller/follow_joint_trajectory ... --feedback`, `ros2 param get` and
`ros2 param set /world_3/joint_trajectory_controller ...`. Exit 0 on success.
"""

from __future__ import annotations

import argparse
import sys

import rclpy
from builtin_interfaces.msg import Duration
from control_msgs.action import FollowJointTrajectory
from controller_manager_msgs.srv import ListControllers, SwitchController
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.action import ActionClient
from rclpy.node import Node
from rclpy.parameter import Parameter
from trajectory_msgs.msg import JointTrajectoryPoint

TIMEOUT = 30.0  # s to find a service or server, and for an answer


def call(node: Node, srv_type: type, name: str, request: object) -> object:
    client = node.create_client(srv_type, name)
    if not client.wait_for_service(timeout_sec=TIMEOUT):
        sys.exit(f"no service {name}")
    future = client.call_async(request)
    rclpy.spin_until_future_complete(node, future, timeout_sec=TIMEOUT)
    if not future.done():
        sys.exit(f"{name}: no answer within {TIMEOUT:g} s")
    return future.result()


def list_controllers(node: Node, cm: str) -> int:
    reply = call(node, ListControllers, f"{cm}/list_controllers", ListControllers.Request())
    for c in reply.controller:
        print(f"{c.name:32s} {c.type:55s} {c.state}")
    return 0


def switch(node: Node, cm: str, activate: list[str], deactivate: list[str]) -> int:
    request = SwitchController.Request(
        activate_controllers=activate, deactivate_controllers=deactivate, strictness=SwitchController.Request.STRICT
    )
    reply = call(node, SwitchController, f"{cm}/switch_controller", request)
    print("ok" if reply.ok else f"refused: {reply.message}")
    return 0 if reply.ok else 1


def goal(node: Node, action: str, joints: list[str], positions: list[float], seconds: float) -> int:
    client = ActionClient(node, FollowJointTrajectory, action)
    if not client.wait_for_server(timeout_sec=TIMEOUT):
        sys.exit(f"no action server {action}")
    g = FollowJointTrajectory.Goal()
    g.trajectory.joint_names = joints
    sec = int(seconds)
    g.trajectory.points = [
        JointTrajectoryPoint(positions=positions, time_from_start=Duration(sec=sec, nanosec=int((seconds - sec) * 1e9)))
    ]

    def feedback(msg: object) -> None:
        error = max(abs(e) for e in msg.feedback.error.positions) if msg.feedback.error.positions else 0.0
        print(f"feedback: largest error {error:.3f}")

    sent = client.send_goal_async(g, feedback_callback=feedback)
    rclpy.spin_until_future_complete(node, sent, timeout_sec=TIMEOUT)
    handle = sent.result()
    if handle is None or not handle.accepted:
        print("goal rejected")
        return 1
    result = handle.get_result_async()
    rclpy.spin_until_future_complete(node, result, timeout_sec=TIMEOUT + seconds)
    if not result.done():
        sys.exit("no result")
    answer = result.result()
    print(f"status {answer.status} error_code {answer.result.error_code} {answer.result.error_string!r}")
    return 0 if answer.status == 4 else 1  # GoalStatus.STATUS_SUCCEEDED


def param(node: Node, controller: str, name: str, value: str | None) -> int:
    """Print a parameter; with `value`, set it first (a number, true/false, else text)."""
    if value is not None:
        typed: object = value
        if value.lower() in ("true", "false"):
            typed = value.lower() == "true"
        else:
            try:
                typed = float(value)
            except ValueError:
                pass
        change = Parameter(name, value=typed).to_parameter_msg()
        reply = call(node, SetParameters, f"{controller}/set_parameters", SetParameters.Request(parameters=[change]))
        if not reply.results[0].successful:
            print(f"refused: {reply.results[0].reason}")
            return 1
    got = call(node, GetParameters, f"{controller}/get_parameters", GetParameters.Request(names=[name]))
    print(f"{name}: {Parameter.from_parameter_msg(ParameterMsg(name=name, value=got.values[0])).value}")
    return 0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("what", choices=["list", "switch", "goal", "param"])
    p.add_argument("--world", type=int, default=0)
    p.add_argument("--namespace", default="world_{i}", help="as batchsim's --namespace ('' : the root)")
    p.add_argument("--activate", default="", help="controllers, comma-separated")
    p.add_argument("--deactivate", default="", help="controllers, comma-separated")
    p.add_argument("--controller", default="joint_trajectory_controller")
    p.add_argument("--joints", default="joint1,joint2,joint3,joint4,joint5,joint6")
    p.add_argument("--positions", default="0.4,-0.3,0.5,0.2,-0.4,0.6")
    p.add_argument("--seconds", type=float, default=1.0, help="the goal's time from start")
    p.add_argument("--name", default="constraints.goal_time", help="param: the parameter")
    p.add_argument("--value", default=None, help="param: set it to this first")
    opts = p.parse_args()
    ns = opts.namespace.format(i=opts.world)
    base = f"/{ns}" if ns else ""
    names = lambda text: [n for n in text.split(",") if n]  # noqa: E731
    rclpy.init()
    node = Node("batchsim_example_controllers")
    try:
        if opts.what == "list":
            return list_controllers(node, f"{base}/controller_manager")
        if opts.what == "switch":
            return switch(node, f"{base}/controller_manager", names(opts.activate), names(opts.deactivate))
        if opts.what == "param":
            return param(node, f"{base}/{opts.controller}", opts.name, opts.value)
        action = f"{base}/{opts.controller}/follow_joint_trajectory"
        return goal(node, action, names(opts.joints), [float(v) for v in names(opts.positions)], opts.seconds)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
