"""`batchsim resim` as a user runs it: a randomized 64-arm fleet recorded over real DDS while a
client sends trajectory goals, a trajectory topic command and resets, then worlds picked from the
file re-run to the bit on cpu; mjx and warp recordings re-run on cpu report where they part and
their horizon; a recording without inputs, another model, a world not recorded: one line, exit 2.
Domains 56-59 belong to this file."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import need
from ros_fleet import Fleet, batchsim_process, domain_id, release_domain, stack_messages

from batchsim.controllers import default_controllers

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"

pytestmark = pytest.mark.ros

ARM_JOINTS = [f"joint{i}" for i in range(1, 7)]
JTC = "joint_trajectory_controller"
RANDOMIZE = """randomize:
  seed: 5
  redraw_on_reset: true
  fields:
    - field: body_mass
      scale: {uniform: [0.7, 1.3]}
    - field: dof_damping
      scale: {uniform: [0.5, 2.0]}
  start_pose:
    add: {normal: [0.0, 0.05]}
"""


def _resim(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "batchsim.cli", "resim", *args], capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A 64-world randomized recording with goals, a topic command and resets in it."""
    ros = stack_messages()
    tmp = tmp_path_factory.mktemp("resim")
    (tmp / "rand.yaml").write_text(RANDOMIZE)
    path = tmp / "run.mcap"
    args = ["--worlds", "64", "--randomize", str(tmp / "rand.yaml"), "--record", str(path), "--duration", "20", "--quiet"]
    args += ["--controllers", str(default_controllers("arm"))]  # past 16 worlds none by default
    with Fleet(domain_id(56), args, tmp / "fleet.log") as fleet:
        js = fleet.latest(ros["JointState"], "/world_13/joint_states")
        fleet.wait(lambda: js.count > 0, 60, "joint_states")
        client = ros["ActionClient"](fleet.node, ros["FJT"], f"/world_13/{JTC}/follow_joint_trajectory")
        assert client.wait_for_server(timeout_sec=40), fleet.log()
        time.sleep(1.0)  # the server sees the client too (tests/test_ros_stack.py says why)

        def trajectory(positions, seconds):
            point = ros["JointTrajectoryPoint"](
                positions=[float(p) for p in positions], time_from_start=ros["Duration"](sec=int(seconds), nanosec=0)
            )
            return ros["JointTrajectory"](joint_names=ARM_JOINTS, points=[point])

        goal = ros["FJT"].Goal(trajectory=trajectory([0.5, -0.4, 0.6, 0.3, -0.5, 0.7], 1))
        assert fleet.send_goal(client, goal).accepted
        fleet.publish(ros["JointTrajectory"], f"/world_40/{JTC}/joint_trajectory", trajectory([-0.6, 0.3, -0.5, 0.2, 0.4, -0.3], 1))
        from std_srvs.srv import Trigger

        time.sleep(1.5)
        # world 40's trajectory controller switched off and on again: the controllers' re-run takes that too
        switch, base = ros["srv"].SwitchController, "/world_40/controller_manager/switch_controller"
        assert fleet.call(switch, base, switch.Request(deactivate_controllers=[JTC], strictness=2)).ok
        time.sleep(0.3)
        assert fleet.call(switch, base, switch.Request(activate_controllers=[JTC], strictness=2)).ok
        assert fleet.call(Trigger, "/world_13/reset", Trigger.Request()).success  # a fresh draw and start
        assert fleet.send_goal(client, ros["FJT"].Goal(trajectory=trajectory([0.2] * 6, 1))).accepted
        time.sleep(0.5)
        # stopped, and a second recording started by the service while the arms move: its worlds
        # start from their state mid-run (warm start and all), not from a reset
        from std_srvs.srv import SetBool

        assert fleet.call(SetBool, "/batchsim/record", SetBool.Request(data=False)).success
        deadline = time.monotonic() + 20  # the first file is being finished meanwhile
        while not (answer := fleet.call(SetBool, "/batchsim/record", SetBool.Request(data=True))).success:
            assert answer.message.startswith("still finishing") and time.monotonic() < deadline, answer.message
            time.sleep(0.2)
        time.sleep(0.3)
        assert fleet.send_goal(client, ros["FJT"].Goal(trajectory=trajectory([-0.3] * 6, 1))).accepted
        fleet.proc.wait(timeout=120)  # --duration: the fleet ends, and the recorder finishes the file
        log = fleet.log()
    assert "recording:" in log, log
    return path, tmp


def test_worlds_of_a_randomized_64_world_recording_rerun_bit_exact(recording):
    path, tmp = recording
    out = tmp / "resim.json"
    done = _resim(str(path), "--worlds", "0,13,40,63", "--tf", "--json", str(out), "--plot", str(tmp / "resim.png"))
    assert done.returncode == 0, done.stderr
    worlds = {r["world"]: r for r in json.loads(out.read_text())["worlds"]}
    frames = {r["world"]: r for r in json.loads(out.read_text())["tf"]}
    for w in (0, 13, 40, 63):  # /tf too: the same body poses, made into the same transforms
        assert frames[w]["exact"] and frames[w]["compared"] > 200 and not frames[w]["unknown"], (w, done.stdout)
    for w in (0, 13, 40, 63):
        assert worlds[w]["exact"] and worlds[w]["compared"] > 200, (w, done.stdout)
        assert f"world {w}: " in done.stdout and "bit-exact" in done.stdout
    # the goals and the topic command moved worlds 13 and 40: the re-run followed them
    assert max(worlds[13]["error"]) == 0 and (tmp / "resim.png").stat().st_size > 1000


def test_the_controllers_rerun_from_the_messages_they_took(recording):
    """The world's JointTrajectoryController again, from its goals and topic trajectory: the same
    commands and ctrl to the bit; with open_loop_control off, the commands part where a goal starts."""
    path, tmp = recording
    out = tmp / "controllers.json"
    done = _resim(str(path), "--worlds", "13,40", "--model", "arm", "--controllers", "--json", str(out))
    assert done.returncode == 0, done.stderr
    verdicts = {v["world"]: v for v in json.loads(out.read_text())["controllers"]}
    assert verdicts[13]["exact"] and verdicts[13]["events"] == 2, done.stdout  # two goals, one after a reset
    assert verdicts[40]["exact"] and verdicts[40]["events"] == 3, done.stdout  # a joint_trajectory message, two switches
    assert "world 13: " in done.stdout and done.stdout.count("bit-exact") == 4
    changed = tmp / "closed_loop.yaml"
    changed.write_text(default_controllers("arm").read_text().replace("open_loop_control: true", "open_loop_control: false"))
    other = _resim(str(path), "--worlds", "13", "--model", "arm", "--controllers", str(changed))
    assert other.returncode == 0, other.stderr
    assert "the commands part at t=" in other.stdout and "/position first" in other.stdout, other.stdout


def test_a_recording_started_mid_run_by_the_service_reruns_bit_exact(recording):
    path, tmp = recording
    second = path.with_name("run_2.mcap")
    out = tmp / "resim2.json"
    done = _resim(str(second), "--worlds", "13,40", "--tf", "--json", str(out))
    assert done.returncode == 0, done.stderr
    worlds = {r["world"]: r for r in json.loads(out.read_text())["worlds"]}
    assert worlds[13]["exact"] and worlds[40]["exact"], done.stdout
    # /tf from the second period on (the first one's poses came from a step before the recording)
    frames = {r["world"]: r for r in json.loads(out.read_text())["tf"]}
    assert frames[13]["exact"] and frames[13]["compared"] == worlds[13]["compared"] - 1, done.stdout
    assert max(np.abs(np.diff(worlds[13]["time"]))) < 0.02  # every period of the world compared
    # its controllers' state at the recording's start is not in the file: not re-run, and said
    mid = _resim(str(second), "--worlds", "40", "--model", "arm", "--controllers")
    assert mid.returncode == 0 and "no fresh start in the recording (it began mid-run)" in mid.stdout, mid.stdout


def test_what_cannot_be_rerun_is_one_line_each(recording):
    path, tmp = recording
    missing = _resim(str(path), "--worlds", "64")
    assert missing.returncode == 2 and missing.stderr.count("\n") == 1
    assert "does not hold world 64 (it recorded worlds 0-63)" in missing.stderr
    other = _resim(str(path), "--worlds", "3", "--model", "rover")
    assert other.returncode == 2 and "--model rover is not the model" in other.stderr and other.stderr.count("\n") == 1
    same = _resim(str(path), "--worlds", "3", "--model", "arm")
    assert same.returncode == 0 and "bit-exact" in same.stdout, same.stderr


def _record(tmp, args, name):
    domain = domain_id(57)
    try:
        proc = batchsim_process([*args, "--record", str(tmp / name), "--quiet"], domain, tmp / f"{name}.log")
        assert proc.wait(timeout=600) == 0, (tmp / f"{name}.log").read_text()
    finally:
        release_domain(domain)
    return tmp / name


def test_a_recording_without_inputs_is_refused_in_one_line(tmp_path):
    path = _record(tmp_path, ["--worlds", "2", "--duration", "0.2", "--rtf", "0", "--no-record-inputs"], "plain.mcap")
    done = _resim(str(path))
    assert done.returncode == 2 and done.stderr.count("\n") == 1
    assert "holds no physics inputs" in done.stderr


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["mjx", "warp"])
def test_a_gpu_backends_recording_rerun_on_cpu_reports_its_divergence_and_horizon(tmp_path, backend):
    need({"mjx": "mujoco.mjx", "warp": "mujoco_warp"}[backend])
    (tmp_path / "rand.yaml").write_text(RANDOMIZE)
    args = ["--backend", backend, "--worlds", "2", "--duration", "1", "--rtf", "0", "--randomize", str(tmp_path / "rand.yaml")]
    path = _record(tmp_path, args, f"{backend}.mcap")
    out = tmp_path / "resim.json"
    done = _resim(str(path), "--tolerance", "1e-3", "--json", str(out))
    assert done.returncode == 0, done.stderr
    results = json.loads(out.read_text())["worlds"]
    assert json.loads(out.read_text())["backend"] == backend
    for r in results:
        assert r["compared"] == 100 and not r["exact"], r  # 1 s at 100 Hz; its own kernels: not to the bit
        t, period, joint, diff = r["first"]
        assert joint in ARM_JOINTS and 0 < diff and period >= 0
        assert r["horizon"] is None or r["horizon"] > 0
        assert np.isfinite(r["max_position"])
    assert "they part at t=" in done.stdout and f"a {backend} recording re-run" in done.stderr


def test_a_world_of_an_arm_and_a_rover_reruns_bit_exact_with_their_controllers(tmp_path):
    """Two robots in every world (examples/fleets/arm_and_rover.yaml): the rover driven over
    cmd_vel, the arm over its joint_trajectory topic. Each robot's joint_states (its own topic,
    its own joint names) is compared, and re-run with the robots' own controllers, the rover's
    odom (the diff drive's estimate from its wheels) comes out as recorded, to the bit."""
    from geometry_msgs.msg import TwistStamped
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    ros = stack_messages()
    path = tmp_path / "cell.mcap"
    fleet_file = str(EXAMPLES / "fleets" / "arm_and_rover.yaml")
    args = ["--fleet", fleet_file, "--worlds", "2", "--record", str(path), "--duration", "8", "--controllers", "default"]
    cmd_vel, jtc = "/world_1/rover/diff_drive_controller/cmd_vel", f"/world_1/arm/{JTC}/joint_trajectory"
    with Fleet(domain_id(58), args, tmp_path / "fleet.log") as fleet:
        odom = fleet.latest(ros["Odometry"], "/world_1/rover/diff_drive_controller/odom")
        arm = fleet.latest(ros["JointState"], "/world_1/arm/joint_states")
        fleet.wait(lambda: odom.count > 0 and arm.count > 0, 60, "odom and the arm's joint_states")
        fleet.advertise(TwistStamped, cmd_vel)
        fleet.advertise(JointTrajectory, jtc)
        fleet.wait_subscribed(cmd_vel)
        fleet.wait_subscribed(jtc)
        point = JointTrajectoryPoint(positions=[0.4, -0.3, 0.5, 0.0, 0.2, 0.0])
        point.time_from_start.sec = 1
        fleet.publish(JointTrajectory, jtc, JointTrajectory(joint_names=ARM_JOINTS, points=[point]))
        drive = TwistStamped()
        drive.twist.linear.x, drive.twist.angular.z = 0.5, 0.8
        for _ in range(30):
            fleet.publish(TwistStamped, cmd_vel, drive)
            time.sleep(0.05)
        fleet.proc.wait(timeout=120)
    from mcap.reader import NonSeekingReader

    with open(path, "rb") as f:  # in log-time order, the inputs among the rest (a replay paces by it)
        logged = [m.log_time for _s, _c, m in NonSeekingReader(f).iter_messages(log_time_order=False)]
    assert logged == sorted(logged)
    out = tmp_path / "cell.json"
    done = _resim(str(path), "--model", fleet_file, "--controllers", "--json", str(out))
    assert done.returncode == 0, done.stderr
    lines = done.stdout
    assert "world 1: 800 rover/diff_drive_controller/odom messages compared: bit-exact" in lines, lines
    assert "world 1: 1600 joint_states compared: bit-exact (every position, velocity and effort of 8 joints" in lines, lines
    result = {r["world"]: r for r in json.loads(out.read_text())["worlds"]}[1]
    assert result["efforts"] == 8 * 799 and any(abs(e) > 1.0 for e in arm.msg.effort), arm.msg.effort  # but at the start
    assert result["joints"][:2] == ["arm/joint1", "arm/joint2"] and "rover/left_wheel_joint" in result["joints"]
    verdicts = {v["world"]: v for v in json.loads(out.read_text())["controllers"]}
    assert verdicts[1]["exact"] and verdicts[1]["events"] > 5, lines
    assert abs(odom.msg.pose.pose.position.x) + abs(odom.msg.pose.pose.position.y) > 0.1  # it drove
    assert abs(arm.msg.position[0] - 0.4) < 0.05, arm.msg.position  # the arm went where it was sent
    # the physics alone, no --model: each robot's joint states, bit-exact
    physics = _resim(str(path), "--worlds", "0,1")
    assert physics.returncode == 0 and physics.stdout.count("1600 joint_states compared: bit-exact (every position, velocity and effort") == 2, physics.stdout
    # a robot's --controllers FILE in a fleet is refused: the fleet file names each robot's own
    refused = _resim(str(path), "--model", fleet_file, "--controllers", str(default_controllers("arm")))
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1 and "a fleet's robots" in refused.stderr
