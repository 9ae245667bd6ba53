"""A fleet served by several bridge workers, and a fleet spread over several processes, over
real DDS. Domains 40-49 belong to this file.

One 64-arm fleet with 3 workers (worlds 0-20, 21-42, 43-63) serves the checks that follow
in file order; the last ones kill a worker and then stop the fleet with SIGTERM. The
trajectory controller holds joints 1-3; joints 4-6 take raw commands.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import need

rclpy = need("rclpy")  # skips where ROS is absent, fails instead under BATCHSIM_FORCE_BACKENDS=1

from builtin_interfaces.msg import Duration  # noqa: E402
from ros_fleet import LOCALHOST, Fleet, alive, bridge_workers, domain_id, segments  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64, Float64MultiArray  # noqa: E402
from std_srvs.srv import SetBool, Trigger  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

pytestmark = pytest.mark.ros

NWORLD = 64
RANGES = [(0, 20), (21, 42), (43, 63)]  # each worker's first and last world
WATCHED = (0, 20, 21, 30, 42, 43, 50, 62, 63)
JTC = "joint_trajectory_controller"
def controllers_yaml(joints: list[str], open_loop: bool = False) -> str:
    """A controller_manager YAML: the joint_state broadcaster and a trajectory controller on `joints`."""
    return f"""
controller_manager:
  ros__parameters:
    update_rate: 100
    joint_state_broadcaster:
      type: joint_state_broadcaster/JointStateBroadcaster
    {JTC}:
      type: joint_trajectory_controller/JointTrajectoryController
{JTC}:
  ros__parameters:
    joints: [{", ".join(joints)}]
    command_interfaces: [position]
    state_interfaces: [position, velocity]
""" + ("    open_loop_control: true\n" if open_loop else "")


CONTROLLERS = controllers_yaml(["joint1", "joint2", "joint3"], open_loop=True)


def sim_time(stamp) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def trajectory(goal, seconds: float = 0.5, joints=("joint1", "joint2", "joint3")) -> JointTrajectory:
    msg = JointTrajectory(joint_names=list(joints))
    msg.points = [JointTrajectoryPoint(positions=list(goal), time_from_start=Duration(sec=0, nanosec=int(seconds * 1e9)))]
    return msg


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    root = tmp_path_factory.mktemp("workers")
    (root / "controllers.yaml").write_text(CONTROLLERS)
    args = ["--worlds", str(NWORLD), "--model", "arm", "--backend", "cpu", "--bridge-workers", "3"]
    args += ["--controllers", str(root / "controllers.yaml")]
    with Fleet(domain_id(40), args, root / "batchsim.log") as f:
        f.js = {w: f.latest(JointState, f"/world_{w}/joint_states") for w in WATCHED}
        f.clock = f.latest(Clock, "/clock")
        f.wait(lambda: all(s.count > 0 for s in f.js.values()), 90, "joint_states from every worker")
        yield f


def position(fleet, world: int, joint: int) -> float:
    return fleet.js[world].msg.position[joint]


def settle(fleet, seconds: float) -> None:
    start = sim_time(fleet.clock.msg.clock)
    fleet.wait(lambda: sim_time(fleet.clock.msg.clock) >= start + seconds, 20, f"{seconds} s of sim time")


def test_every_world_has_its_topics_and_services_whichever_worker_serves_it(fleet):
    node = fleet.node
    workers = {f"batchsim_{a}_{b}" for a, b in RANGES}

    def complete() -> bool:  # discovery settles over a moment: wait for it, as for the topics
        if not workers <= {name for name, _ in node.get_node_names_and_namespaces()}:
            return False
        services = {name for name, _ in node.get_service_names_and_types()}
        return all(
            node.count_publishers(f"/world_{w}/joint_states") == 1
            and node.count_subscribers(f"/world_{w}/commands") == 1
            and node.count_subscribers(f"/world_{w}/{JTC}/joint_trajectory") == 1
            and f"/world_{w}/reset" in services
            for w in range(NWORLD)
        ) and {"/batchsim/reset", "/batchsim/pause", "/batchsim/step"} <= services

    fleet.wait(complete, 30, "every world's topics and services")
    assert node.count_publishers("/clock") == 1
    # with workers, the physics process never loads rclpy
    assert "rclpy" not in open(f"/proc/{fleet.proc.pid}/maps").read()


def test_a_command_to_the_last_world_of_the_last_worker_moves_only_that_world(fleet):
    topic = f"/world_{NWORLD - 1}/actuators/joint5/command"  # created once a publisher appears
    fleet.publish_until(Float64, topic, Float64(data=0.7), lambda: position(fleet, 63, 4) > 0.6, 20)
    for w in WATCHED[:-1]:
        assert abs(position(fleet, w, 4)) < 0.02, f"world_{w} moved"


def test_a_trajectory_drives_a_world_of_a_later_worker(fleet):
    goal = [0.4, -0.3, 0.5]
    topic = f"/world_50/{JTC}/joint_trajectory"
    fleet.advertise(JointTrajectory, topic)
    fleet.wait_subscribed(topic)
    fleet.publish(JointTrajectory, topic, trajectory(goal))
    fleet.wait(lambda: np.abs(np.array(fleet.js[50].msg.position[:3]) - goal).max() < 0.04, 20, "world_50 at its goal")
    for w in (0, 21, 43, 62):
        assert np.abs(np.array(fleet.js[w].msg.position[:3])).max() < 0.02, f"world_{w} moved"


def test_reset_pause_and_step_across_workers(fleet):
    # a world of the last worker, reset through its own service
    reply = fleet.call(Trigger, f"/world_{NWORLD - 1}/reset", Trigger.Request())
    assert reply.success, reply.message
    settle(fleet, 0.3)
    assert abs(position(fleet, 63, 4)) < 0.02, "world_63 was not reset"
    assert position(fleet, 50, 0) > 0.35, "world_50 was reset too"

    # pause (worker 0's service) freezes every worker's worlds
    assert fleet.call(SetBool, "/batchsim/pause", SetBool.Request(data=True)).success
    time.sleep(0.3)
    frozen = sim_time(fleet.clock.msg.clock)
    stamps = {w: sim_time(fleet.js[w].msg.header.stamp) for w in (0, 30, 63)}
    time.sleep(0.3)
    assert sim_time(fleet.clock.msg.clock) == frozen
    assert all(sim_time(fleet.js[w].msg.header.stamp) == stamps[w] for w in stamps)

    # a reset while paused is published at once (world_50 held its goal until now)
    count = fleet.js[50].count
    assert fleet.call(Trigger, "/batchsim/reset", Trigger.Request()).success
    fleet.wait(lambda: fleet.js[50].count > count, 5, "world_50's reset published while paused")
    assert np.abs(np.array(fleet.js[50].msg.position[:3])).max() < 0.02
    assert sim_time(fleet.clock.msg.clock) == frozen

    # a step answers after it ran, with the new time, which every worker publishes
    reply = fleet.call(Trigger, "/batchsim/step", Trigger.Request())
    assert reply.success, reply.message
    assert reply.message == f"stepped to sim time {frozen + 0.01:.6f} s"
    fleet.wait(lambda: all(sim_time(fleet.js[w].msg.header.stamp) > stamps[w] for w in stamps), 5, "the step's state")
    time.sleep(0.2)
    assert sim_time(fleet.clock.msg.clock) == pytest.approx(frozen + 0.01, abs=1e-9)
    for w in stamps:
        assert sim_time(fleet.js[w].msg.header.stamp) == pytest.approx(frozen + 0.01, abs=1e-9)
    assert fleet.call(SetBool, "/batchsim/pause", SetBool.Request(data=False)).success
    settle(fleet, 0.1)


def test_a_stopped_worker_is_reported_and_said_to_answer_again(fleet):
    """kill -STOP on a worker (issue 23: its worlds went quiet and nobody said so): noticed
    within 2 s naming its worlds, shown in the other workers' /diagnostics; SIGCONT: said to
    answer again, and its worlds publish again (the restart of one that never comes back:
    test_a_hung_worker_is_killed_and_restarted)."""
    workers = bridge_workers(fleet.proc.pid)
    diag = fleet.diagnostics()
    os.kill(workers[2], signal.SIGSTOP)
    try:
        fleet.wait(lambda: "bridge worker 2 (pid" in fleet.log() and "has not answered" in fleet.log(), 2.5, "the hang noticed")
        assert "/world_43 .. /world_63 are not served" in fleet.log()
        fleet.wait(lambda: diag.world("bridge_worker_2") is not None, 5, "the hang in /diagnostics")
        status = diag.world("bridge_worker_2")
        assert status.level == status.ERROR and "/world_43 .. /world_63 are not served" in status.message
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(workers[2], signal.SIGCONT)
    before = fleet.js[63].count
    fleet.wait(lambda: "bridge worker 2 answers again" in fleet.log(), 5, "the worker answering again")
    fleet.wait(lambda: fleet.js[63].count > before + 5, 30, "world_63's joint_states again")


def test_a_stopped_physics_process_is_said_and_said_to_run_again(fleet):
    """kill -STOP on the physics process (issue 47's review: every topic went quiet and nobody
    said so): worker 0 says so within PHYSICS_STALL s and shows it in /diagnostics; SIGCONT: said
    to run again, and the worlds publish again."""
    from ros_bridge.protocol.liveness import PHYSICS_STALL

    diag = fleet.diagnostics()
    os.kill(fleet.proc.pid, signal.SIGSTOP)
    try:
        fleet.wait(lambda: "the physics process has not finished a period for" in fleet.log(), PHYSICS_STALL + 3, "the stop said")
        fleet.wait(lambda: diag.world("batchsim") is not None, 5, "the stop in /diagnostics")
        status = diag.world("batchsim")
        assert status.level == status.ERROR and "has not run a period" in status.message
    finally:
        os.kill(fleet.proc.pid, signal.SIGCONT)
    before = fleet.js[0].count
    fleet.wait(lambda: "the physics process runs again" in fleet.log(), 5, "said to run again")
    fleet.wait(lambda: fleet.js[0].count > before + 5, 30, "world_0's joint_states again")


def test_a_goal_in_flight_when_its_worker_dies_is_told_aborted_by_the_next_one(tmp_path):
    """A goal accepted by a worker that was then killed never got a result: its client waited
    forever (issue 47's review). The restarted worker finds it held and tells its client ABORTED
    on the action's status topic."""
    from action_msgs.msg import GoalStatus
    from control_msgs.action import FollowJointTrajectory
    from rclpy.action import ActionClient

    args = ["--worlds", "2", "--controllers", "default", "--bridge-workers", "1"]
    with Fleet(domain_id(44), args, tmp_path / "batchsim.log") as fleet:
        fleet.wait_started()
        client = ActionClient(fleet.node, FollowJointTrajectory, "/world_1/joint_trajectory_controller/follow_joint_trajectory")
        assert client.wait_for_server(timeout_sec=40)
        time.sleep(1.0)
        goal = FollowJointTrajectory.Goal()
        goal.trajectory = JointTrajectory(
            joint_names=[f"joint{k}" for k in range(1, 7)],
            points=[JointTrajectoryPoint(positions=[0.3] * 6, time_from_start=Duration(sec=20))],
        )
        handle = fleet.send_goal(client, goal)
        assert handle.accepted
        fleet.wait(lambda: handle.status == GoalStatus.STATUS_EXECUTING, 10, "the goal executing")
        worker = bridge_workers(fleet.proc.pid)
        os.kill(next(iter(worker.values())), signal.SIGKILL)
        fleet.wait(lambda: handle.status == GoalStatus.STATUS_ABORTED, 40, "the goal told ABORTED")
        fleet.wait(lambda: "is told ABORTED on the action's status topic" in fleet.log(), 10, "the line that says so")


def test_a_killed_worker_is_restarted_and_its_worlds_come_back(fleet):
    workers = bridge_workers(fleet.proc.pid)
    assert sorted(workers) == [0, 1, 2]
    topic = "/world_30/actuators/joint6/command"
    fleet.publish_until(Float64, topic, Float64(data=-0.6), lambda: position(fleet, 30, 5) < -0.5, 30)
    before = {w: fleet.js[w].count for w in (0, 30, 63)}
    os.kill(workers[1], signal.SIGKILL)
    # noticed within a second (and a little for this loaded machine)
    fleet.wait(lambda: "bridge worker 1 (pid" in fleet.log(), 1.5, "the death noticed")
    log = fleet.log()
    assert "/world_21 .. /world_42 hold their last commands; restarting it" in log, log[-2000:]
    fleet.wait(lambda: "bridge worker 1 is back" in fleet.log(), 60, "the worker back")
    # its worlds publish and take commands again, having held their last; the others never stopped
    fleet.wait(lambda: fleet.js[30].count > before[30] + 5, 30, "world_30's joint_states again")
    assert position(fleet, 30, 5) < -0.5, "world_30 did not hold its last command"
    assert fleet.js[0].count > before[0] + 5 and fleet.js[63].count > before[63] + 5
    fleet.publish_until(Float64, topic, Float64(data=0.3), lambda: position(fleet, 30, 5) > 0.25, 30)
    assert abs(position(fleet, 21, 5)) < 0.02


def test_sigterm_stops_every_process_within_2_s_and_leaves_no_segment(fleet):
    pid = fleet.proc.pid
    workers = list(bridge_workers(pid).values())
    assert len(workers) == 3 and segments(pid)
    start = time.monotonic()
    fleet.proc.send_signal(signal.SIGTERM)
    fleet.proc.wait(timeout=10)
    deadline = start + 2.0
    while any(alive(p) for p in workers) and time.monotonic() < deadline + 1:
        time.sleep(0.02)
    took = time.monotonic() - start
    assert fleet.proc.returncode == 0, fleet.log()[-2000:]
    assert not [p for p in workers if alive(p)], "orphaned workers"
    assert took < 2.0, f"took {took:.2f} s"
    assert segments(pid) == []
    log = fleet.log()
    assert "Traceback" not in log and "callback failed" not in log, log[-3000:]


# --- lockstep across workers, with a controller holding every interface ---
LOCKSTEP_CONTROLLERS = controllers_yaml([f"joint{i}" for i in range(1, 7)])


def test_lockstep_waits_for_every_worlds_trajectory_on_every_worker(tmp_path):
    """The trajectory controller holds every interface: lockstep waits for each world's
    trajectory, as it waits for raw commands."""
    (tmp_path / "c.yaml").write_text(LOCKSTEP_CONTROLLERS)
    n = 6
    args = ["--worlds", str(n), "--model", "arm", "--backend", "cpu", "--bridge-workers", "3", "--rtf", "0"]
    args += ["--lockstep", "--lockstep-timeout", "30", "--controllers", str(tmp_path / "c.yaml")]
    joints = [f"joint{i}" for i in range(1, 7)]
    with Fleet(domain_id(41), args, tmp_path / "lockstep.log") as f:
        clock = f.latest(Clock, "/clock")
        topics = [f"/world_{w}/{JTC}/joint_trajectory" for w in range(n)]
        for t in topics:  # no message yet: one that reaches some worlds would open a later period's gate
            f.advertise(JointTrajectory, t)
        for t in topics:
            f.wait_subscribed(t)

        def send(worlds, value):
            for w in worlds:
                f.publish(JointTrajectory, topics[w], trajectory([value] * 6, 1.0, joints))

        f.wait(lambda: clock.msg is not None, 20, "the first period's clock")
        time.sleep(0.5)
        for k in range(3):
            before = sim_time(clock.msg.clock)
            send(range(n), 0.05 * (k + 1))
            f.wait(lambda b=before: sim_time(clock.msg.clock) > b, 10, "one period")
            time.sleep(0.3)
            assert sim_time(clock.msg.clock) == pytest.approx(before + 0.01, abs=1e-9)
        before = sim_time(clock.msg.clock)
        send(range(n - 1), 0.2)  # world_5 (the last worker's) says nothing: the period waits
        time.sleep(0.6)
        assert sim_time(clock.msg.clock) == before
        send([n - 1], 0.2)
        f.wait(lambda: sim_time(clock.msg.clock) > before, 10, "the period once world_5 sent its trajectory")
        time.sleep(0.3)
        assert sim_time(clock.msg.clock) == pytest.approx(before + 0.01, abs=1e-9)
        assert f.close() == 0


# --- one fleet over several processes (as over several hosts) ---
def _batchsim(domain: int, args: list[str], log) -> subprocess.Popen:
    env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(domain), "PYTHONUNBUFFERED": "1"}
    cmd = [sys.executable, "-m", "batchsim.cli", "--quiet", "--controllers", "none", "--backend", "cpu", *args]
    return subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)


def test_processes_with_world_offsets_form_one_fleet_and_overlaps_are_refused(tmp_path):
    domain = domain_id(42)
    second_log = open(tmp_path / "second.log", "w")
    with Fleet(domain, ["--worlds", "3", "--model", "arm"], tmp_path / "first.log") as f:
        second = _batchsim(domain, ["--worlds", "3", "--world-offset", "3", "--no-clock", "--bridge-workers", "1"], second_log)
        try:
            js = {w: f.latest(JointState, f"/world_{w}/joint_states") for w in range(6)}
            f.wait(lambda: all(s.count > 0 for s in js.values()), 60, "joint_states of world_0 .. world_5")
            assert f.node.count_publishers("/clock") == 1
            command = Float64MultiArray(data=[0.6, 0, 0, 0, 0, 0])
            f.publish_until(Float64MultiArray, "/world_4/commands", command, lambda: js[4].msg.position[0] > 0.5, 20)
            for w in (0, 2, 3, 5):
                assert abs(js[w].msg.position[0]) < 0.02, f"world_{w} moved"

            # a process that would serve world_4 again, and a second /clock: refused, naming the other
            for args, expected in (
                (["--worlds", "2", "--world-offset", "4", "--no-clock"], "already serves /world_4 and 1 more (node /batchsim_3_5"),
                (["--worlds", "2", "--world-offset", "10"], "already publishes /clock (node /batchsim_0_2"),
            ):
                out = subprocess.run(
                    [sys.executable, "-m", "batchsim.cli", "--controllers", "none", "--backend", "cpu", *args],
                    env={**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(domain)},
                    capture_output=True, text=True, timeout=120,
                )  # fmt: skip
                assert out.returncode == 2, out.stderr
                lines = out.stderr.strip().splitlines()
                assert len(lines) == 1 and expected in lines[0], out.stderr
            assert second.poll() is None and f.proc.poll() is None
        finally:
            second.send_signal(signal.SIGINT)
            second.wait(timeout=20)
            second_log.close()
        assert second.returncode == 0, (tmp_path / "second.log").read_text()
        assert f.close() == 0


def test_a_second_fleet_started_on_the_same_domain_by_mistake_is_refused(tmp_path):
    with Fleet(domain_id(43), ["--worlds", "2", "--model", "arm"], tmp_path / "first.log") as f:
        f.wait_started()
        out = subprocess.run(
            [sys.executable, "-m", "batchsim.cli", "--controllers", "none", "--worlds", "2"],
            env={**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(f.domain)},
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert out.returncode == 2, out.stderr
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and "already serves /world_0 and 1 more (node /batchsim_0_1" in lines[0], out.stderr
        assert f.proc.poll() is None
        assert f.close() == 0


@pytest.mark.parametrize("ctrl_c", [False, True], ids=["sigterm", "ctrl-c"])
def test_sigterm_or_ctrl_c_while_the_workers_start_stops_them_and_removes_the_segment(ctrl_c):
    """Ctrl-C: SIGINT to the terminal's whole process group."""
    domain = domain_id(44)
    env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(domain), "PYTHONUNBUFFERED": "1"}
    cmd = [sys.executable, "-m", "batchsim.cli", "--worlds", "4", "--controllers", "none", "--bridge-workers", "2"]
    proc = subprocess.Popen(cmd, env=env, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        workers: list[int] = []
        while not workers and time.monotonic() < deadline and proc.poll() is None:
            workers = list(bridge_workers(proc.pid).values())
            time.sleep(0.01)
        assert workers and segments(proc.pid), "no worker started"
        if ctrl_c:
            os.killpg(proc.pid, signal.SIGINT)
        else:
            proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    # interrupted during start-up: the documented exit codes, 128 + the signal (docs/cli.md)
    assert proc.returncode == (130 if ctrl_c else 143), err
    assert "Traceback" not in err and "leaked" not in err, err
    assert not [p for p in workers if alive(p)], "orphaned workers"
    assert segments(proc.pid) == []
