"""The shipped policy (examples/policies/arm_reach.onnx) as every world's controller, over real
DDS: `batchsim` with the policy's controllers YAML and its randomization in a subprocess, each
world's target sent on `/world_<i>/arm_reach_controller/command`, and a world switched from the
policy to the joint_trajectory_controller and back over `controller_manager/switch_controller`.
Domains 90-91 belong to this file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import need

rclpy = need("rclpy")
need("onnxruntime")

from ros_fleet import Fleet, domain_id, stack_messages  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402

pytestmark = pytest.mark.ros

EXAMPLES = Path(__file__).resolve().parent.parent / "examples" / "policies"
NWORLD = 8
POLICY, JTC = "arm_reach_controller", "joint_trajectory_controller"


@pytest.fixture(scope="module")
def arms(tmp_path_factory):
    log = tmp_path_factory.mktemp("policy") / "batchsim.log"
    args = ["--worlds", str(NWORLD), "--model", "arm", "--backend", "cpu",
            "--controllers", str(EXAMPLES / "arm_reach.yaml"), "--randomize", str(EXAMPLES / "randomize.yaml")]  # fmt: skip
    with Fleet(domain_id(90), args, log) as fleet:
        fleet.js = [fleet.latest(JointState, f"/world_{w}/joint_states") for w in range(NWORLD)]
        fleet.wait(lambda: all(s.count > 0 for s in fleet.js), 60, "joint_states")
        yield fleet


def positions(fleet, world: int) -> np.ndarray:
    msg = fleet.js[world].msg
    return np.array([msg.position[list(msg.name).index(f"joint{i}")] for i in range(1, 7)])


def test_the_policy_follows_each_worlds_target_sent_over_ros(arms):
    rng = np.random.default_rng(1)
    targets = rng.uniform(-0.8, 0.8, size=(NWORLD, 6))
    for w in range(NWORLD):
        topic = f"/world_{w}/{POLICY}/command"
        arms.advertise(Float64MultiArray, topic)
        arms.wait_subscribed(topic)
        arms.publish(Float64MultiArray, topic, Float64MultiArray(data=targets[w].tolist()))

    def reached() -> int:
        return sum(np.abs(positions(arms, w) - targets[w]).max() < 0.1 for w in range(NWORLD))

    # most randomized worlds: masses, friction, damping and gains drawn per world
    arms.wait(lambda: reached() >= NWORLD - 1, timeout=30, what="the worlds at their targets")
    # a command of the wrong length is refused by name, and the world keeps its target
    arms.publish(Float64MultiArray, f"/world_0/{POLICY}/command", Float64MultiArray(data=[0.0, 0.0]))
    arms.wait(
        lambda: "2 values" in arms.log() and POLICY in arms.log(), timeout=10, what="the refusal's line"
    )
    assert np.abs(positions(arms, 0) - targets[0]).max() < 0.15


def test_a_world_switches_from_the_policy_to_the_trajectory_controller_and_back(arms):
    m = stack_messages()
    srv = m["srv"]
    base = "/world_3/controller_manager"
    switch = srv.SwitchController.Request(
        activate_controllers=[JTC], deactivate_controllers=[POLICY], strictness=2
    )
    assert arms.call(srv.SwitchController, f"{base}/switch_controller", switch).ok
    listed = arms.call(srv.ListControllers, f"{base}/list_controllers", srv.ListControllers.Request())
    states = {c.name: c.state for c in listed.controller}
    assert states[POLICY] == "inactive" and states[JTC] == "active"
    # the policy's command no longer moves world 3; the JTC holds it
    held = positions(arms, 3)
    arms.publish(Float64MultiArray, f"/world_3/{POLICY}/command", Float64MultiArray(data=[0.5] * 6))
    arms.wait(lambda: arms.js[3].count > 0, 5)
    import time

    time.sleep(1.5)
    assert np.abs(positions(arms, 3) - held).max() < 0.1
    other = arms.call(
        srv.ListControllers, "/world_4/controller_manager/list_controllers", srv.ListControllers.Request()
    )
    assert {c.name: c.state for c in other.controller}[POLICY] == "active"
    back = srv.SwitchController.Request(
        activate_controllers=[POLICY], deactivate_controllers=[JTC], strictness=2
    )
    assert arms.call(srv.SwitchController, f"{base}/switch_controller", back).ok
    target = [0.3, -0.3, 0.4, 0.2, -0.2, 0.1]
    arms.publish(Float64MultiArray, f"/world_3/{POLICY}/command", Float64MultiArray(data=target))
    arms.wait(
        lambda: np.abs(positions(arms, 3) - target).max() < 0.1,
        timeout=20,
        what="world 3 following the policy again",
    )
