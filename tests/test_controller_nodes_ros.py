"""Every world's controllers and controller_manager as ROS nodes, as ros2_control makes them
(ros_bridge/worker/controller_nodes.py; issue 47): `/world_1/joint_trajectory_controller` and
`/world_1/controller_manager` in the graph, the controller's YAML parameters readable through the
standard parameter services, those upstream's trajectory controller takes at run time settable per
world, and any other set refused with the reason; upstream's
`controller_manager.test_utils.check_controllers_running` (tests/ros_fleet.py, line for line: it
waits for those nodes before it asks list_controllers); `--controller-nodes off` makes none. A batchsim
subprocess of the shipped arm over real DDS. Domain 66.
"""

from __future__ import annotations

import time

import pytest
from conftest import need
from ros_fleet import Fleet, check_controllers_running, domain_id

rclpy = need("rclpy")
pytestmark = pytest.mark.ros

JTC = "joint_trajectory_controller"
CONTROLLERS = ["joint_state_broadcaster", JTC, "wrist_ft_broadcaster"]


def _call(fleet, srv_type, name, request):
    return fleet.call(srv_type, name, request, timeout=20.0)


def test_each_controller_is_a_node_with_its_parameters(tmp_path):
    from controller_manager_msgs.srv import ListControllers
    from rcl_interfaces.msg import Parameter, ParameterValue
    from rcl_interfaces.srv import GetParameters, SetParameters

    with Fleet(domain_id(66), ["--worlds", "2", "--controllers", "default"], tmp_path / "log") as fleet:
        fleet.wait_started()
        check_controllers_running(fleet, CONTROLLERS, "/world_1")  # upstream's helper, line for line
        assert ("controller_manager", "/world_0") in fleet.node.get_node_names_and_namespaces()
        listed = _call(fleet, ListControllers, "/world_1/controller_manager/list_controllers", ListControllers.Request())
        assert {c.name: c.state for c in listed.controller} == dict.fromkeys(CONTROLLERS, "active")
        got = _call(fleet, GetParameters, f"/world_1/{JTC}/get_parameters", GetParameters.Request(names=["joints", "command_interfaces"]))
        assert list(got.values[0].string_array_value) == [f"joint{k}" for k in range(1, 7)]
        assert list(got.values[1].string_array_value) == ["position"]
        cm = _call(fleet, GetParameters, "/world_1/controller_manager/get_parameters",
                   GetParameters.Request(names=["update_rate", f"{JTC}.type"]))  # fmt: skip
        assert cm.values[0].integer_value == 100
        assert cm.values[1].string_value == "joint_trajectory_controller/JointTrajectoryController"
        change = Parameter(name="open_loop_control", value=ParameterValue(type=1, bool_value=False))
        refused = _call(fleet, SetParameters, f"/world_1/{JTC}/set_parameters", SetParameters.Request(parameters=[change]))
        assert not refused.results[0].successful and "restart" in refused.results[0].reason
        _set_at_run_time(fleet)


def _set_at_run_time(fleet):
    """What upstream's JointTrajectoryController takes at run time is set in one world: world 1
    takes a partial goal after `allow_partial_joints_goal` is set there, world 0 still refuses it;
    a bad value is refused with the reason, and the node keeps its value."""
    from control_msgs.action import FollowJointTrajectory
    from rcl_interfaces.msg import Parameter, ParameterValue
    from rcl_interfaces.srv import GetParameters, SetParameters
    from rclpy.action import ActionClient
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    def set_(world, name, value):
        change = Parameter(name=name, value=value)
        reply = _call(fleet, SetParameters, f"/world_{world}/{JTC}/set_parameters", SetParameters.Request(parameters=[change]))
        return reply.results[0]

    def get(world, name):
        return _call(fleet, GetParameters, f"/world_{world}/{JTC}/get_parameters", GetParameters.Request(names=[name])).values[0]

    assert get(1, "constraints.goal_time").double_value == 0.0  # declared with upstream's default
    assert set_(1, "allow_partial_joints_goal", ParameterValue(type=1, bool_value=True)).successful
    assert get(1, "allow_partial_joints_goal").bool_value and not get(0, "allow_partial_joints_goal").bool_value
    bad = set_(1, "constraints.goal_time", ParameterValue(type=3, double_value=-1.0))
    assert not bad.successful and ">= 0" in bad.reason, bad.reason
    assert get(1, "constraints.goal_time").double_value == 0.0
    point = JointTrajectoryPoint(positions=[0.3])
    point.time_from_start.nanosec = 500_000_000
    goal = FollowJointTrajectory.Goal(trajectory=JointTrajectory(joint_names=["joint1"], points=[point]))
    outcomes = {}
    for world in (0, 1):
        client = ActionClient(fleet.node, FollowJointTrajectory, f"/world_{world}/{JTC}/follow_joint_trajectory")
        assert client.wait_for_server(timeout_sec=40), fleet.log()
        time.sleep(1.0)  # the server's answer to a client it has not matched yet is dropped (test_ros_stack.py)
        handle = fleet.send_goal(client, goal)
        if handle.accepted:
            future = handle.get_result_async()
            fleet.wait(future.done, 40, "the goal's result")
            outcomes[world] = future.result()
    assert outcomes[1].status == 4, outcomes[1]  # SUCCEEDED
    assert 0 not in outcomes or ("allow_partial_joints_goal" in outcomes[0].result.error_string), outcomes[0]


def test_no_controller_nodes_when_turned_off(tmp_path):
    with Fleet(domain_id(66), ["--worlds", "2", "--controllers", "default", "--controller-nodes", "off"], tmp_path / "log") as fleet:
        fleet.wait_started()
        time.sleep(2.0)
        names = fleet.node.get_node_names_and_namespaces()
        assert not any(name == JTC for name, _ in names), names
