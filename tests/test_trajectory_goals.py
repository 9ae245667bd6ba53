"""FollowJointTrajectory goals in the trajectory controller, without ROS: what the bridge's
action server hands the controller (TrajectoryBatch with goal tags and tolerances) and the
per-world outcomes it reads back, on the shipped arm (position servos, cpu backend).

Upstream semantics (ros2_controllers' JointTrajectoryController, jazzy) the tests pin down:
path tolerances while the trajectory runs, goal tolerances once past its last point, a goal
time tolerance of 0 waiting for the goal tolerance, holding position after a violation or a
cancel, and -1 erasing a default tolerance.
"""

from __future__ import annotations

import textwrap

import numpy as np

import batchsim
from batchsim.controllers import load_controllers
from batchsim.controllers.topics import trajectory_batch
from batchsim.controllers.trajectory import GoalOutcome
from batchsim.loop import SimLoop

ARM_JOINTS = [f"joint{i}" for i in range(1, 7)]
TARGET = np.array([0.5, -0.4, 0.6, 0.3, -0.5, 0.8])


def arm_yaml(constraints: str = "") -> str:
    """models/arm.yaml's trajectory controller, with a `constraints` block."""
    block = textwrap.indent(textwrap.dedent(constraints), " " * 4)
    return (
        textwrap.dedent("""\
        controller_manager:
          ros__parameters:
            update_rate: 100
            joint_trajectory_controller:
              type: joint_trajectory_controller/JointTrajectoryController
        joint_trajectory_controller:
          ros__parameters:
            joints: [joint1, joint2, joint3, joint4, joint5, joint6]
            command_interfaces: [position]
            state_interfaces: [position, velocity]
            open_loop_control: true
        """)
        + block
    )


def running(nworld: int, yaml: str | None = None):
    sim = batchsim.make("arm", nworld, "cpu", nthread=1)
    sim.configure()
    sim.activate()
    manager = load_controllers(yaml or arm_yaml(), sim.spec, nworld)
    loop = SimLoop(sim, control_rate=manager.update_rate, rtf=0, participants=[manager])
    loop.run_period()
    jtc = manager["joint_trajectory_controller"]
    return sim, manager, loop, jtc


def positions(sim) -> np.ndarray:
    names = sim.export_state_interfaces()
    return sim.state[:, [names.index(f"{j}/position") for j in ARM_JOINTS]].copy()


def send_goal(jtc, world, tag, times, points, *, path=None, goal=None, goal_time=None):
    """One goal for `world`, as the bridge hands it over: tolerances per joint (position,
    velocity, acceleration), NaN where the goal names no tolerance."""
    nj = len(ARM_JOINTS)

    def table(values):
        if values is None:
            return None
        full = np.full((1, nj, 3), np.nan)
        for joint, tolerance in values.items():
            full[0, joint] = tolerance
        return full

    message = (world, ARM_JOINTS, np.asarray(times, float), np.asarray(points, float), None, None, 0.0)
    batch, kept, rejected = trajectory_batch(
        ARM_JOINTS,
        [message],
        goals=[tag],
        path_tolerance=table(path),
        goal_tolerance=table(goal),
        goal_time_tolerance=None if goal_time is None else [goal_time],
    )
    assert kept == [0] and not rejected
    assert jtc.set_trajectories(batch) == []


def run_until(loop, t):
    while loop.sim_time < t - 1e-9:
        loop.run_period()


def run_while_active(loop, jtc, world, limit):
    while jtc.outcome[world] == GoalOutcome.ACTIVE and loop.sim_time < limit:
        loop.run_period()


def test_a_goal_succeeds_in_world_2_of_4_and_the_others_stay_put():
    sim, _, loop, jtc = running(4)
    start = positions(sim)
    t0 = loop.sim_time
    # the position servos sag under gravity by up to ~0.03 rad: 0.05 is reachable
    send_goal(jtc, 2, 17, [1.0], [TARGET], goal={k: (0.05, 0, 0) for k in range(6)})
    assert jtc.goal.tolist() == [0, 0, 17, 0]
    assert jtc.outcome.tolist() == [GoalOutcome.NONE] * 2 + [GoalOutcome.ACTIVE, GoalOutcome.NONE]
    run_until(loop, t0 + 0.5)
    assert jtc.outcome[2] == GoalOutcome.ACTIVE and jtc.executing[2]
    run_while_active(loop, jtc, 2, t0 + 3.0)
    assert jtc.outcome[2] == GoalOutcome.SUCCEEDED
    assert loop.sim_time < t0 + 1.2  # at the last point, as soon as it is within tolerance
    assert jtc.goal[2] == 17 and jtc.outcome_joint[2] == -1
    np.testing.assert_allclose(positions(sim)[2], TARGET, atol=0.05)
    others = [0, 1, 3]
    np.testing.assert_allclose(positions(sim)[others], start[others], atol=1e-9)
    assert (jtc.outcome[others] == GoalOutcome.NONE).all() and (jtc.goal[others] == 0).all()


def test_a_too_tight_goal_tolerance_waits_the_goal_time_then_is_violated_and_holds():
    sim, _, loop, jtc = running(2)
    t0 = loop.sim_time
    # 1e-6 rad: the sagging servos never get that close
    send_goal(jtc, 1, 5, [0.5], [TARGET], goal={k: (1e-6, 0, 0) for k in range(6)}, goal_time=0.4)
    run_until(loop, t0 + 0.5 + 0.3)  # past the last point, within the goal time tolerance
    assert jtc.outcome[1] == GoalOutcome.ACTIVE and not jtc.executing[1]
    run_while_active(loop, jtc, 1, t0 + 3.0)
    assert jtc.outcome[1] == GoalOutcome.GOAL_TOLERANCE_VIOLATED
    assert 0.5 + 0.4 < loop.sim_time - t0 < 0.5 + 0.4 + 0.05
    assert 0 <= jtc.outcome_joint[1] < 6
    # upstream holds the measured position, not the last point
    held = jtc.reference_position[1].copy()
    np.testing.assert_allclose(held, jtc.feedback_position[1], atol=1e-12)
    assert np.abs(held - TARGET).max() > 1e-6
    run_until(loop, loop.sim_time + 0.3)
    np.testing.assert_array_equal(jtc.reference_position[1], held)
    assert jtc.outcome[1] == GoalOutcome.GOAL_TOLERANCE_VIOLATED and jtc.goal[1] == 5


def test_without_a_goal_time_tolerance_a_goal_outside_its_tolerance_stays_active():
    # upstream: "If set to zero, the controller will wait a potentially infinite amount of time"
    _, _, loop, jtc = running(1)
    t0 = loop.sim_time
    send_goal(jtc, 0, 3, [0.5], [TARGET], goal={0: (1e-6, 0, 0)})
    run_until(loop, t0 + 2.0)
    assert jtc.outcome[0] == GoalOutcome.ACTIVE and not jtc.executing[0]
    np.testing.assert_allclose(jtc.reference_position[0], TARGET)  # still commanding the point


def test_a_path_tolerance_violation_aborts_the_goal_and_holds_the_world():
    sim, _, loop, jtc = running(3)
    t0 = loop.sim_time
    # a fast move: the position servo of joint2 lags its reference by far more than 1e-3 rad
    send_goal(jtc, 0, 9, [0.3, 2.0], [TARGET, TARGET], path={1: (1e-3, -1, -1)})
    run_while_active(loop, jtc, 0, t0 + 2.0)
    assert jtc.outcome[0] == GoalOutcome.PATH_TOLERANCE_VIOLATED
    assert loop.sim_time - t0 < 0.3  # while moving, not at the end
    assert jtc.outcome_joint[0] == 1  # the only joint with a path tolerance
    assert not jtc.executing[0]
    held = jtc.reference_position[0].copy()
    np.testing.assert_allclose(held, jtc.feedback_position[0], atol=1e-12)
    run_until(loop, loop.sim_time + 0.5)
    np.testing.assert_array_equal(jtc.reference_position[0], held)
    assert np.abs(positions(sim)[0] - TARGET).max() > 0.1  # it never went on to the point


def test_cancel_stops_the_world_where_it_is():
    sim, _, loop, jtc = running(2)
    t0 = loop.sim_time
    send_goal(jtc, 1, 4, [2.0], [TARGET])
    run_until(loop, t0 + 0.8)
    jtc.cancel(np.array([1]), np.array([99]))  # not its goal: nothing happens
    jtc.cancel(np.array([0]), np.array([4]))
    assert jtc.outcome.tolist() == [GoalOutcome.NONE, GoalOutcome.ACTIVE]
    jtc.cancel(np.array([1]), np.array([4]))
    assert jtc.outcome[1] == GoalOutcome.CANCELED and jtc.goal[1] == 4
    here = jtc.feedback_position[1].copy()
    run_until(loop, t0 + 1.5)
    assert not jtc.executing[1]
    np.testing.assert_array_equal(jtc.reference_position[1], here)
    # the arm stops within a few hundredths of where it was canceled, far from the point
    np.testing.assert_allclose(positions(sim)[1], here, atol=0.05)
    assert np.abs(positions(sim)[1] - TARGET).max() > 0.1
    jtc.cancel(np.array([1]), np.array([4]))  # canceling twice changes nothing
    assert jtc.outcome[1] == GoalOutcome.CANCELED


def test_a_newer_goal_or_a_topic_trajectory_replaces_the_goal():
    _, _, loop, jtc = running(2)
    t0 = loop.sim_time
    send_goal(jtc, 0, 7, [2.0], [TARGET])
    run_until(loop, t0 + 0.3)
    send_goal(jtc, 0, 8, [0.5], [TARGET / 2], goal={k: (0.05, 0, 0) for k in range(6)})
    assert jtc.goal[0] == 8 and jtc.outcome[0] == GoalOutcome.ACTIVE
    run_while_active(loop, jtc, 0, t0 + 3.0)
    assert jtc.goal[0] == 8 and jtc.outcome[0] == GoalOutcome.SUCCEEDED
    np.testing.assert_allclose(jtc.reference_position[0], TARGET / 2)
    send_goal(jtc, 0, 10, [1.0], [TARGET])
    jtc.set_trajectory(0, ARM_JOINTS, [1.0], [TARGET / 3])  # a plain topic trajectory
    assert jtc.goal[0] == 0 and jtc.outcome[0] == GoalOutcome.NONE
    run_until(loop, loop.sim_time + 1.5)
    assert jtc.outcome[0] == GoalOutcome.NONE


def test_reset_aborts_active_goals():
    sim, manager, loop, jtc = running(3)
    t0 = loop.sim_time
    for w, tag in ((0, 1), (1, 2)):
        send_goal(jtc, w, tag, [1.0], [TARGET], goal={k: (0.05, 0, 0) for k in range(6)})
    run_until(loop, t0 + 0.4)
    loop.reset([1, 2])
    assert jtc.outcome.tolist() == [GoalOutcome.ACTIVE, GoalOutcome.ABORTED, GoalOutcome.NONE]
    assert jtc.goal.tolist() == [1, 2, 0] and not jtc.executing[1]
    run_while_active(loop, jtc, 0, t0 + 3.0)
    assert jtc.outcome.tolist() == [GoalOutcome.SUCCEEDED, GoalOutcome.ABORTED, GoalOutcome.NONE]


def test_deactivating_the_controller_ends_its_goal_as_deactivated_not_reset():
    """Before, a goal of a controller deactivated by switch_controller ended ABORTED, which the
    bridge words "the world was reset" (issue 47's review)."""
    sim, manager, loop, jtc = running(3)
    t0 = loop.sim_time
    for w, tag in ((0, 1), (1, 2)):
        send_goal(jtc, w, tag, [1.0], [TARGET], goal={k: (0.05, 0, 0) for k in range(6)})
    run_until(loop, t0 + 0.4)
    manager.switch(deactivate=["joint_trajectory_controller"], worlds=[1])
    run_until(loop, t0 + 0.5)
    assert jtc.outcome.tolist() == [GoalOutcome.ACTIVE, GoalOutcome.DEACTIVATED, GoalOutcome.NONE]
    loop.reset([0])
    assert jtc.outcome[0] == GoalOutcome.ABORTED  # a reset is still a reset


def test_the_yaml_constraints_are_the_defaults_and_a_misspelt_key_warns():
    yaml = arm_yaml("""\
        constraints:
          stopped_velocity_tolerance: 0.02
          goal_time: 0.25
          goal_tme: 1.0
          joint2:
            trajectory: 0.001
            goal: 0.05
            goall: 0.1
        """)
    sim, manager, loop, jtc = running(2, yaml)
    c = jtc.constraints
    assert (c.stopped_velocity_tolerance, c.goal_time) == (0.02, 0.25)
    assert c.trajectory.tolist() == [0, 0.001, 0, 0, 0, 0] and c.goal.tolist() == [0, 0.05, 0, 0, 0, 0]
    warned = " ".join(manager.warnings)
    assert "constraints.goal_tme" in warned and "constraints.joint2.goall" in warned
    assert "constraints.goal_time" not in warned.replace("constraints.goal_tme", "")
    t0 = loop.sim_time
    # no tolerances of its own: joint2's path tolerance from the YAML aborts the fast move
    send_goal(jtc, 0, 1, [0.3], [TARGET])
    # the same goal with joint2's path tolerance erased (-1) runs to its end
    send_goal(jtc, 1, 2, [0.3], [TARGET], path={1: (-1, 0, 0)})
    run_while_active(loop, jtc, 0, t0 + 2.0)
    run_while_active(loop, jtc, 1, t0 + 2.0)
    assert jtc.outcome[0] == GoalOutcome.PATH_TOLERANCE_VIOLATED and jtc.outcome_joint[0] == 1
    assert jtc.outcome[1] == GoalOutcome.SUCCEEDED
    # the defaults alone load without warnings
    assert running(1)[1].warnings == []


def test_tolerances_set_at_run_time_change_one_world_from_its_next_goal():
    """A set_parameters on `/world_1/joint_trajectory_controller` (Controller.set_parameters):
    world 1's next goal takes the new defaults, world 0 keeps the YAML's, and a goal already
    running keeps the tolerances it started with, as upstream's update re-reads its parameters."""
    _, _, loop, jtc = running(2)
    assert jtc.runtime_parameters()["constraints.goal_time"] == 0.0
    tight = {f"constraints.{j}.goal": 1e-6 for j in ARM_JOINTS} | {"constraints.goal_time": 0.2}
    t0 = loop.sim_time
    send_goal(jtc, 1, 1, [0.5], [TARGET])  # started with the YAML's tolerances (none)
    assert jtc.set_parameters(np.array([1]), tight) == ""
    run_while_active(loop, jtc, 1, t0 + 2.0)
    assert jtc.outcome[1] == GoalOutcome.SUCCEEDED  # its own tolerances, not the new ones
    t1 = loop.sim_time
    for world in (0, 1):
        send_goal(jtc, world, 2, [0.5], [TARGET * 0.5])
    run_until(loop, t1 + 0.5 + 0.2 + 0.1)
    assert jtc.outcome[0] == GoalOutcome.SUCCEEDED
    assert jtc.outcome[1] == GoalOutcome.GOAL_TOLERANCE_VIOLATED  # 1e-6 rad within 0.2 s: never


def test_a_bad_or_read_only_parameter_set_at_run_time_is_refused_and_changes_nothing():
    _, _, loop, jtc = running(2)
    why = jtc.set_parameters(np.array([1]), {"constraints.goal_time": -1.0, "allow_partial_joints_goal": True})
    assert "constraints.goal_time" in why and ">= 0" in why
    assert not jtc.allow_partial.any()  # nothing of a refused set is applied
    why = jtc.set_parameters(np.array([1]), {"joints": ["joint1"]})
    assert "'joints'" in why and "read-only" in why and "restart" in why
    assert "does not act on it" in jtc.set_parameters(np.array([0]), {"cmd_timeout": 1.0})
    assert "joint9" in jtc.set_parameters(np.array([0]), {"gains.joint9.p": 1.0})
    assert jtc.set_parameters(np.array([1]), {"allow_partial_joints_goal": True}) == ""
    assert jtc.allow_partial.tolist() == [False, True]
    message = (1, ["joint1"], np.array([0.5]), np.array([[0.3]]), None, None, 0.0)
    batch, kept, _ = trajectory_batch(ARM_JOINTS, [message, (0, *message[1:])])
    rejected = jtc.set_trajectories(batch)
    assert [k for k, _ in rejected] == [1] and "allow_partial_joints_goal" in rejected[0][1]
