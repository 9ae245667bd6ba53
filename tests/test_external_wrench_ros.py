"""mujoco_ros2_control's ExternalWrenchPlugin over real DDS: the demo robot (test_robot.urdf and its
scene, upstream's files unchanged) with the plugin's YAML, run by `batchsim` as a fleet of two
worlds in a subprocess. Domain 96 belongs to this file.

The service is `/world_<i>/external_wrench/apply_wrench` (the plugin's sub-node namespace under
the world's; `/external_wrench/apply_wrench` for one world at the root, as upstream's docs call
it). A push on world 1's cube1 (free, resting on the floor) lifts that cube and not world 0's;
the answer comes once the wrench has run, in sim time: while the fleet is paused it waits, and
step_simulation lets it through. The pushes are upward (the cube's z, upright at rest): a push
along x at the centre of mass would tip the cube (friction 1, as high as wide) and leave its
frame anywhere. A request naming an unknown body is refused whole, upstream's
words, nothing pushed; an empty one is answered at once. The cubes' poses come from each world's
tf (`/world_<i>/tf`, frame `world_<i>/cube1`).
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from ros_fleet import Fleet, domain_id

pytestmark = pytest.mark.ros

DEMOS = Path(__file__).parent / "upstream" / "mujoco_ros2_control_demos"
URDF = DEMOS / "demo_resources" / "robot" / "test_robot.urdf"
PLUGINS = """/**:
  ros__parameters:
    mujoco_plugins:
      external_wrench:
        type: "mujoco_ros2_control_plugins/ExternalWrenchPlugin"
        force_arrow_scale: 0.01
        torque_arrow_scale: 0.1
"""
NODE = "/mujoco_ros2_control_node"


class Cube:
    """cube1's latest pose (x, z) and its stamp, from one world's tf."""

    def __init__(self, world: int):
        self.frame = f"world_{world}/cube1"
        self.x = self.z = self.stamp = None

    def __call__(self, msg) -> None:
        for t in msg.transforms:
            if t.child_frame_id == self.frame:
                self.x, self.z = t.transform.translation.x, t.transform.translation.z
                self.stamp = t.header.stamp.sec + 1e-9 * t.header.stamp.nanosec


def _request(ms, mm, *entries):
    """(body, force along the body's z, duration) per wrench."""
    request = ms.ApplyExternalWrench.Request()
    for body, fz, seconds in entries:
        wrench = mm.ExternalWrench()
        wrench.wrench.header.frame_id = body
        wrench.wrench.wrench.force.z = fz
        wrench.duration.sec, wrench.duration.nanosec = int(seconds), round((seconds % 1) * 1e9)
        request.wrenches.external_wrenches.append(wrench)
    return request


def test_a_push_in_world_1_moves_its_cube_and_no_other(tmp_path):
    import mujoco_ros2_control_msgs.msg as mm
    import mujoco_ros2_control_msgs.srv as ms
    from tf2_msgs.msg import TFMessage

    plugins = tmp_path / "plugins.yaml"
    plugins.write_text(PLUGINS)
    args = ["--ros2-control", str(URDF), "--sensors", str(plugins), "--worlds", "2", "--backend", "cpu"]
    with Fleet(domain_id(96), args, tmp_path / "batchsim.log") as fleet:
        cubes = [Cube(w) for w in range(2)]
        for w, cube in enumerate(cubes):
            fleet.node.create_subscription(TFMessage, f"/world_{w}/tf", cube, 10)
        fleet.wait(lambda: all(c.stamp is not None for c in cubes), 60, "cube1 on /world_0/tf and /world_1/tf")
        assert "ExternalWrenchPlugin" not in fleet.log()  # run, not warned of
        service = "/world_1/external_wrench/apply_wrench"
        # refused whole: cube1 is fine, cube9 is not in the model, so cube1 is not pushed either
        reply = fleet.call(ms.ApplyExternalWrench, service, _request(ms, mm, ("cube1", 2.0, 0.2), ("cube9", 1.0, 0.0)))
        assert (reply.success, reply.message) == (False, "Body 'cube9' not found in MuJoCo model.")
        reply = fleet.call(ms.ApplyExternalWrench, service, ms.ApplyExternalWrench.Request())
        assert (reply.success, reply.message) == (True, "No wrenches provided; nothing applied.")
        settled = cubes[1].stamp + 0.3
        fleet.wait(lambda: cubes[1].stamp > settled, 30, "0.3 s of sim time")
        start = [(c.x, c.z) for c in cubes]
        assert abs(start[1][1] + 2.45) < 1e-3  # on the floor: not pushed by the refused request
        # 2 N up for 0.2 s (0.1 kg: 1 N beyond its weight): answered once run, 0.2 m up by then
        reply = fleet.call(ms.ApplyExternalWrench, service, _request(ms, mm, ("cube1", 2.0, 0.2)))
        assert (reply.success, reply.message) == (True, "Applied 1 wrench(es) successfully.")
        fleet.wait(lambda: cubes[1].z - start[1][1] > 0.15, 10, "world 1's cube1 up")
        assert abs(cubes[1].x - start[1][0]) < 1e-3  # straight up: the force along the body's z
        # it falls back and settles; world 0's never moved
        landed = cubes[1].stamp + 1.5
        fleet.wait(lambda: cubes[1].stamp > landed, 30, "1.5 s more of sim time")
        assert abs(cubes[1].z - start[1][1]) < 1e-2, (start[1], cubes[1].z)
        assert abs(cubes[0].x - start[0][0]) < 1e-4 and abs(cubes[0].z - start[0][1]) < 1e-4, (start[0], cubes[0].z)
        # paused, the answer waits for the sim time to pass; 100 physics steps (0.2 s) let it through
        assert fleet.call(ms.SetPause, f"{NODE}/set_pause", ms.SetPause.Request(paused=True)).success
        client = fleet.node.create_client(ms.ApplyExternalWrench, service)
        future = client.call_async(_request(ms, mm, ("cube1", 2.0, 0.1)))
        time.sleep(1.5)
        assert not future.done()
        z = cubes[1].z
        reply = fleet.call(ms.StepSimulation, f"{NODE}/step_simulation", ms.StepSimulation.Request(steps=100))
        assert reply.success, reply.message
        fleet.wait(future.done, 10, "the answer after the steps")
        assert future.result().success, future.result().message
        fleet.wait(lambda: cubes[1].z > z + 0.02, 10, "world 1's cube1 up again")
        assert fleet.call(ms.SetPause, f"{NODE}/set_pause", ms.SetPause.Request(paused=False)).success
