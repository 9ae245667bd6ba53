"""mujoco_ros2_control's demo 05 (05_base_velocity_plugin.launch.py: a mobile base driven by the
BaseVelocityPlugin from /cmd_vel), its files unchanged, run by `batchsim` as a fleet of two
worlds in a subprocess over real DDS. Domain 94 belongs to this file.

The launch file becomes `batchsim --model scene_mobile_base.xml --ros2-control mobile_base.urdf
--controllers controllers_base_velocity.yaml --sensors mujoco_ros2_control_plugins_base_velocity.yaml`.
The plugin's `cmd_vel_topic: /cmd_vel` is each world's `/world_<i>/cmd_vel` (exactly /cmd_vel
with one world at the root namespace); a Twist there moves that world's base and no other's,
and the base stops once cmd_timeout (0.5 s of sim time) passes without one. The base's pose
is read from `/world_<i>/odom`. World 0's arm swings meanwhile (its position controller,
`/world_0/arm_position_controller/commands`), and its base, held at zero velocity, stays put.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from ros_fleet import Fleet, domain_id

pytestmark = pytest.mark.ros

DEMOS = Path(__file__).parent / "upstream" / "mujoco_ros2_control_demos"
DEMO_05 = [
    "--model", str(DEMOS / "demo_resources" / "scenes" / "scene_mobile_base.xml"),
    "--ros2-control", str(DEMOS / "demo_resources" / "mobile_base" / "mobile_base.urdf"),
    "--controllers", str(DEMOS / "config" / "controllers_base_velocity.yaml"),
    "--sensors", str(DEMOS / "config" / "mujoco_ros2_control_plugins_base_velocity.yaml"),
    "--worlds", "2", "--backend", "cpu",
]  # fmt: skip


def _xy(sink) -> tuple[float, float]:
    p = sink.msg.pose.pose.position
    return p.x, p.y


def _stamp(sink) -> float:
    return sink.msg.header.stamp.sec + 1e-9 * sink.msg.header.stamp.nanosec


def test_a_twist_on_one_worlds_cmd_vel_moves_that_base_only(tmp_path):
    from geometry_msgs.msg import Twist
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    with Fleet(domain_id(94), DEMO_05, tmp_path / "demo05.log") as fleet:
        odom = [fleet.latest(Odometry, f"/world_{w}/odom") for w in range(2)]
        fleet.wait(lambda: all(o.count > 0 for o in odom), 60, "/world_0/odom and /world_1/odom")
        assert "BaseVelocityPlugin" not in fleet.log()  # run, not warned of
        start = [_xy(o) for o in odom]
        arm = fleet.latest(JointState, "/world_0/joint_states")
        # the MJCF's joint range is 0.7 degrees (its compiler's default unit): the servo pushes the
        # arm to 0.064 rad against the limit, the base holding its reaction
        swung = lambda: arm.msg is not None and arm.msg.position[list(arm.msg.name).index("arm_joint")] > 0.05  # noqa: E731
        topic = "/world_0/arm_position_controller/commands"
        fleet.publish_until(Float64MultiArray, topic, Float64MultiArray(data=[0.7]), swung, 30, "world 0's arm moving")
        forward = Twist()
        forward.linear.x = 0.5
        # the base starts at yaw 0: body +x is world +x
        fleet.publish_until(
            Twist, "/world_1/cmd_vel", forward, lambda: _xy(odom[1])[0] - start[1][0] > 0.3, 30, "world 1's base moving"
        )
        x, y = _xy(odom[1])
        assert abs(y - start[1][1]) < 0.02, (start[1], (x, y))
        # no more commands: after cmd_timeout (sim time) the base is held still
        stopped_from = _stamp(odom[1]) + 1.0
        fleet.wait(lambda: _stamp(odom[1]) > stopped_from, 30, "1 s of sim time")
        x1, stamp1 = _xy(odom[1])[0], _stamp(odom[1])
        fleet.wait(lambda: _stamp(odom[1]) > stamp1 + 0.5, 30, "0.5 s more of sim time")
        assert abs(_xy(odom[1])[0] - x1) < 1e-3
        # world 0's base was never commanded: it stayed where it started, its arm swinging
        x0, y0 = _xy(odom[0])
        assert abs(x0 - start[0][0]) < 3e-4 and abs(y0 - start[0][1]) < 3e-4, (start[0], (x0, y0))  # free: 9e-4 in 2 s
