"""The controller_manager's per-world activation and switch_controller (ros2_control jazzy's
semantics), on the cpu backend with the shipped arm and its models/arm.yaml."""

from __future__ import annotations

import numpy as np
import pytest

import batchsim
from batchsim.controllers import Strictness, default_controllers, load_controllers
from batchsim.loop import SimLoop

JOINTS = [f"joint{i}" for i in range(1, 7)]
JTC = "joint_trajectory_controller"
COLS = np.arange(6)  # the arm's command interfaces are joint1..6/position, in order

# a forward_command_controller and a JTC on the same joints: the JTC (second) loads inactive
BOTH = """\
controller_manager:
  ros__parameters:
    update_rate: 100
    forward_position_controller:
      type: forward_command_controller/ForwardCommandController
    joint_trajectory_controller:
      type: joint_trajectory_controller/JointTrajectoryController
forward_position_controller:
  ros__parameters:
    joints: [joint1, joint2, joint3, joint4, joint5, joint6]
    interface_name: position
joint_trajectory_controller:
  ros__parameters:
    joints: [joint1, joint2, joint3, joint4, joint5, joint6]
    command_interfaces: [position]
    state_interfaces: [position, velocity]
"""


def running(nworld: int, yaml_source=None):
    sim = batchsim.make("arm", nworld, "cpu", nthread=1)
    sim.configure()
    sim.activate()
    manager = load_controllers(yaml_source or default_controllers("arm"), sim.spec, nworld)
    loop = SimLoop(sim, control_rate=manager.update_rate, rtf=0, participants=[manager])
    loop.run_period()
    return sim, manager, loop


def run_for(loop: SimLoop, seconds: float) -> None:
    end = loop.sim_time + seconds
    while loop.sim_time < end - 1e-9:
        loop.run_period()


def send(jtc, worlds, value: float, duration: float = 0.5) -> None:
    for w in worlds:
        jtc.set_trajectory(w, JOINTS, [duration], [np.full(6, value)])


def both(tmp_path):
    path = tmp_path / "controllers.yaml"
    path.write_text(BOTH)
    return running(3, str(path))


def test_deactivated_in_world_1_keeps_its_last_command_while_0_and_2_move_then_reactivated_holds():
    sim, manager, loop = running(3)
    jtc = manager[JTC]
    send(jtc, range(3), 0.2)
    run_for(loop, 0.7)
    result = manager.switch([1], deactivate=[JTC], strictness=Strictness.STRICT)
    assert result.ok and list(result.deactivated) == [JTC] and result.deactivated[JTC].tolist() == [1]
    assert manager.active(JTC).tolist() == [True, False, True]
    with pytest.raises(ValueError):  # a read-only view
        manager.active(JTC)[1] = True
    last = sim.command[1, COLS].copy()
    np.testing.assert_allclose(last, 0.2)
    send(jtc, range(3), -0.3)  # world 1's is ignored: its controller is inactive there
    run_for(loop, 1.0)
    np.testing.assert_array_equal(sim.command[1, COLS], last)
    np.testing.assert_allclose(sim.command[[0, 2]][:, COLS], -0.3)
    assert manager.hardware_interfaces(1).command_interfaces[0].is_claimed is False
    assert manager.hardware_interfaces(0).command_interfaces[0].claimed_by == JTC
    assert [i.state(1) for i in manager.describe() if i.name == JTC] == ["inactive"]

    result = manager.switch([1], activate=[JTC], strictness=Strictness.STRICT)
    assert result.ok and result.activated[JTC].tolist() == [1]
    loop.run_period()
    # it starts from the current state: holds where world 1 is, the ignored trajectory dropped
    here = jtc.feedback_position[1].copy()
    assert not jtc.executing[1] and not jtc.pending[1]
    np.testing.assert_allclose(sim.command[1, COLS], here, atol=1e-9)
    run_for(loop, 1.0)
    np.testing.assert_allclose(sim.command[1, COLS], here, atol=1e-9)
    positions = [sim.spec.state_interfaces.index(f"{j}/position") for j in JOINTS]
    assert (sim.state[1, positions] > 0.15).all()  # never went for the ignored -0.3


def test_strict_with_an_unknown_name_fails_and_changes_nothing():
    sim, manager, loop = running(3)
    result = manager.switch([0, 2], activate=[], deactivate=[JTC, "nope"], strictness=Strictness.STRICT)
    assert not result.ok
    assert "'nope'" in result.message and "no controller with this name exists" in result.message
    assert manager.active(JTC).all() and not result.deactivated
    # STRICT: deactivating where it is not active fails too; BEST_EFFORT skips those worlds
    assert manager.switch([1], deactivate=[JTC], strictness=2).ok
    strict = manager.switch([0, 1], deactivate=[JTC], strictness=2)
    assert not strict.ok and "not active in world 1" in strict.message
    assert manager.active(JTC).tolist() == [True, False, True]
    best = manager.switch([0, 1], deactivate=[JTC], strictness="best_effort")
    assert best.ok and best.deactivated[JTC].tolist() == [0]
    assert manager.active(JTC).tolist() == [False, False, True]


def test_best_effort_drops_unknown_and_impossible_ones_and_does_the_rest(tmp_path):
    sim, manager, loop = both(tmp_path)
    result = manager.switch(
        [0],
        activate=["nope", JTC],
        deactivate=["forward_position_controller"],
        strictness=Strictness.BEST_EFFORT,
    )
    assert result.ok and "'nope'" in result.message
    assert result.activated[JTC].tolist() == [0]
    # activating it again where it is active: skipped, nothing to do, still ok
    again = manager.switch([0], activate=[JTC], strictness=1)
    assert again.ok and "already active in world 0" in again.message and not again.activated
    assert not manager.switch([0], activate=[JTC], strictness=2).ok
    # only unknown names: not ok (upstream: no controller of the list exists)
    assert not manager.switch([0], activate=["nope"], strictness=1).ok
    # a conflicting one is skipped in the worlds where it conflicts, the rest is done
    mixed = manager.switch([0, 1], activate=[JTC], strictness=1)
    assert (
        mixed.ok
        and mixed.activated == {}
        and "claimed by controller 'forward_position_controller'" in mixed.message
    )
    assert manager.active(JTC).tolist() == [True, False, False]


def test_a_conflicting_activation_fails_naming_the_interface_and_both_controllers(tmp_path):
    sim, manager, loop = both(tmp_path)
    assert manager.active("forward_position_controller").all() and not manager.active(JTC).any()
    [warning] = [w for w in manager.warnings if "starts inactive" in w]
    assert f"controller '{JTC}'" in warning and "'joint1/position'" in warning
    assert "claimed by 'forward_position_controller'" in warning
    result = manager.switch([2], activate=[JTC], strictness=Strictness.STRICT)
    assert not result.ok
    for part in (f"'{JTC}'", "'joint1/position'", "'forward_position_controller'", "world 2"):
        assert part in result.message, (part, result.message)
    assert not manager.active(JTC).any() and manager.active("forward_position_controller").all()


def test_one_request_moves_the_claimed_interfaces_between_controllers(tmp_path, monkeypatch):
    sim, manager, loop = both(tmp_path)
    switches = []
    monkeypatch.setattr(
        sim, "perform_command_mode_switch", lambda start, stop=(): switches.append((start, stop))
    )
    fcc, jtc = manager["forward_position_controller"], manager[JTC]
    for w in range(3):
        fcc.set_commands(w, np.full(6, 0.25))
    run_for(loop, 0.5)
    jtc.set_trajectory(0, JOINTS, [0.5], [np.full(6, -0.2)])  # inactive in world 0: ignored

    result = manager.switch([1], activate=[JTC], deactivate=["forward_position_controller"], strictness=2)
    assert result.ok and result.activated[JTC].tolist() == [1]
    assert result.deactivated["forward_position_controller"].tolist() == [1]
    assert result.started == () and result.stopped == ()  # still claimed: no mode switch
    assert manager.hardware_interfaces(1).command_interfaces[3].claimed_by == JTC
    assert manager.hardware_interfaces(0).command_interfaces[3].claimed_by == "forward_position_controller"
    loop.run_period()
    assert switches == []
    here = jtc.feedback_position[1].copy()
    np.testing.assert_allclose(sim.command[1, COLS], here, atol=1e-9)  # the JTC holds world 1
    jtc.set_trajectory(1, JOINTS, [0.5], [np.full(6, -0.1)])
    for w in range(3):
        fcc.set_commands(w, np.full(6, 0.4))  # world 1's is no longer this controller's to drive
    run_for(loop, 1.0)
    np.testing.assert_allclose(sim.command[1, COLS], -0.1)
    np.testing.assert_allclose(sim.command[[0, 2]][:, COLS], 0.4)

    # off everywhere: its interfaces stop being claimed; on again: they start
    assert not manager.switch(None, deactivate=[JTC], strictness=2).ok  # inactive in worlds 0 and 2
    off = manager.switch(None, deactivate=[JTC], strictness=1)
    assert off.ok and off.stopped == () and off.deactivated[JTC].tolist() == [1]
    off = manager.switch([0, 2], deactivate=["forward_position_controller"], strictness=2)
    assert off.stopped == tuple(f"{j}/position" for j in JOINTS)
    on = manager.switch([0, 1, 2], activate=[JTC], strictness=2)
    assert on.started == tuple(f"{j}/position" for j in JOINTS)
    loop.run_period()
    assert switches == [([], list(off.stopped)), (list(on.started), [])]
    # what world 0 was sent while the JTC was inactive there was dropped on activation
    assert not jtc.executing.any()
    np.testing.assert_allclose(sim.command[0, COLS], jtc.feedback_position[0], atol=1e-9)


def test_queries_for_the_services():
    sim, manager, loop = running(2)
    info = {i.name: i for i in manager.describe()}
    assert list(info) == list(manager.controllers)
    jtc = info[JTC]
    assert jtc.type == "joint_trajectory_controller/JointTrajectoryController"
    assert jtc.command_interfaces == tuple(f"{j}/position" for j in JOINTS)
    assert "joint1/velocity" in jtc.state_interfaces and jtc.update_rate == 100.0 and jtc.is_async is False
    assert info["joint_state_broadcaster"].command_interfaces == ()
    hw = manager.hardware_interfaces(0)
    assert [i.name for i in hw.command_interfaces] == sim.export_command_interfaces()
    assert all(i.is_claimed for i in hw.command_interfaces)
    assert [i.name for i in hw.state_interfaces] == sim.export_state_interfaces()
    types = dict(manager.controller_types())
    assert types[jtc.type] == "controller_interface::ControllerInterface"
    assert "forward_command_controller/ForwardCommandController" in types
    with pytest.raises(ValueError):
        manager.switch([5], deactivate=[JTC], strictness=2)


def test_switch_reads_its_worlds_as_the_contract_does():
    """A mask, indices in any order (reported ascending); the contract's errors: a world out of
    range, listed twice, or not an integer (issue 42: one reading of world lists)."""
    sim, manager, loop = running(3)
    off = manager.switch([2, 0], deactivate=[JTC], strictness=2)
    assert off.ok and off.deactivated[JTC].tolist() == [0, 2]
    on = manager.switch(np.array([True, False, True]), activate=[JTC], strictness=2)
    assert on.ok and on.activated[JTC].tolist() == [0, 2]
    for worlds, message in [([3], "world 3 is out of range"), ([1, 1], "world 1 is listed more than once"), ([0.5], "must be integers")]:
        with pytest.raises(ValueError, match=message):
            manager.switch(worlds, deactivate=[JTC], strictness=2)
    assert manager.active(JTC).all()


def test_a_fully_inactive_controller_is_not_updated(tmp_path):
    sim, manager, loop = both(tmp_path)
    jtc = manager[JTC]
    jtc.set_trajectory(0, JOINTS, [0.3], [np.full(6, 0.5)])
    before = jtc.time
    run_for(loop, 0.5)
    assert jtc.time == before and not jtc.executing.any()
    np.testing.assert_allclose(sim.command[:, COLS], 0.0, atol=1e-12)
