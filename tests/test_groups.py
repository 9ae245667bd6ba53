"""Fleets of several models (batchsim.fleet.groups): groups of worlds, each its own fleet file's
world, one system per group, numbered as one fleet and stepped by one loop (SimLoop.join).
No ROS here (tests/test_groups_ros.py has the bridge)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import yaml

import batchsim
from batchsim.fleet import FleetError
from batchsim.fleet.groups import read_groups
from batchsim.loop import OptionError, SimLoop

ARM = {"name": "arm", "model": "arm"}
ROVER = {"name": "rover", "model": "rover", "pose": [0.0, 2.0, 0.0, 0.0]}


def _groups(tmp_path, groups, **top):
    """A fleet file of `groups` in tmp_path; a group's `fleet: <name>` gets a file of its own."""
    items = []
    for g in groups:
        g = dict(g)
        if isinstance(g.get("fleet"), dict):
            sub = tmp_path / f"{g['name']}.yaml"
            sub.write_text(yaml.safe_dump(g["fleet"]))
            g["fleet"] = sub.name
        items.append(g)
    path = tmp_path / "groups.yaml"
    path.write_text(yaml.safe_dump({**top, "groups": items}))
    return path


@pytest.fixture
def two_groups(tmp_path):
    """arms: 2 worlds of an arm alone (a fleet file of its own); yard: 3 worlds of an arm and a rover, inline."""
    return _groups(
        tmp_path,
        [
            {"name": "arms", "worlds": 2, "fleet": {"robots": [ARM]}},
            {"name": "yard", "worlds": 3, "robots": [ARM, ROVER]},
        ],
        name="depot",
    )


def test_groups_are_numbered_one_after_the_other(two_groups):
    fleet = read_groups(two_groups)
    assert fleet.name == "depot" and fleet.nworld == 5
    arms, yard = fleet.groups
    assert (arms.name, arms.world_range, arms.key) == ("arms", range(0, 2), "groups[0]")
    assert (yard.name, yard.world_range) == ("yard", range(2, 5))
    assert [r.name for r in yard.fleet.robots] == ["arm", "rover"]


@pytest.mark.parametrize(
    "group, line",
    [
        ({"name": "a", "worlds": 0, "robots": [ARM]}, r"groups\[0\]\.worlds: a whole number of worlds, at least 1, got 0"),
        ({"name": "a", "worlds": 2.5, "robots": [ARM]}, r"groups\[0\]\.worlds: a whole number of worlds, at least 1, got 2\.5"),
        ({"name": "2a", "worlds": 1, "robots": [ARM]}, r"groups\[0\]\.name: '2a' is not a valid ROS name"),
        ({"worlds": 1, "robots": [ARM]}, r"groups\[0\]\.name: None is not a valid ROS name"),
        ({"name": "a", "worlds": 1}, r"groups\[0\]: give one of fleet .* and robots .*, not both or neither"),
        ({"name": "a", "worlds": 1, "robots": [ARM], "fleet": "x.yaml"}, r"groups\[0\]: give one of fleet"),
        ({"name": "a", "worlds": 1, "robots": [ARM], "speed": 2}, r"groups\[0\]\.speed: unknown key"),
        ({"name": "a", "worlds": 1, "robots": [{"name": "arm"}]}, r"groups\[0\]: robots\[0\]: model is missing"),
        ({"name": "a", "worlds": 1, "fleet": "missing.yaml"}, r"groups\[0\]\.fleet: .*missing\.yaml"),
    ],
)
def test_a_bad_group_is_one_line_naming_the_file_and_the_key(tmp_path, group, line):
    path = _groups(tmp_path, [group])
    with pytest.raises(FleetError, match=line) as caught:
        read_groups(path)
    assert str(path) in str(caught.value) and "\n" not in str(caught.value)


def test_two_groups_of_one_name_are_refused(tmp_path):
    path = _groups(tmp_path, [{"name": "a", "worlds": 1, "robots": [ARM]}, {"name": "a", "worlds": 2, "robots": [ARM]}])
    with pytest.raises(FleetError, match=r"groups\[1\]\.name: 'a' is taken by groups\[0\]"):
        read_groups(path)


def test_make_says_a_fleet_of_groups_is_several_systems(two_groups):
    with pytest.raises(FleetError, match="a fleet of several groups of worlds is several systems: .*make_groups"):
        batchsim.make(two_groups, 4, "cpu")


def _loops(pairs, **kw):
    loops = [SimLoop(sim, rtf=0, **kw) for _, sim in pairs]
    for loop in loops[1:]:
        loops[0].join(loop)
    return loops


def test_one_loop_steps_every_group_at_one_sim_time(two_groups):
    pairs = batchsim.make_groups(two_groups, "cpu")
    for _, sim in pairs:
        sim.configure(), sim.activate()
    (arms, a), (yard, y) = pairs
    assert (a.nworld, y.nworld) == (2, 3) and len(y.spec.robots) == 2
    loops = _loops(pairs)
    leader = loops[0]
    assert leader.nworld == 5 and leader.members == loops and loops[1].leader is leader
    for _ in range(5):
        leader.run_period()
    a.read(), y.read()
    assert leader.sim_time == pytest.approx(loops[1].sim_time) == pytest.approx(5 * leader.period)
    assert np.allclose(a.time, leader.sim_time) and np.allclose(y.time, leader.sim_time)
    # pause, steps and stop are the fleet's: a joined loop's pause pauses the leader
    loops[1].pause(True)
    assert leader.paused
    loops[1].step_physics(3)
    assert leader.pending_steps == 3
    leader.abort_steps(), leader.pause(False)
    # a reset of every world of the leader resets every group's; a group's own, only its worlds
    loops[1].reset([1])
    y.read()
    assert y.time[1] == 0.0 and y.time[0] > 0 and a.time[0] > 0
    leader.reset()
    a.read(), y.read()
    assert (a.time == 0).all() and (y.time == 0).all()
    for _, sim in pairs:
        sim.shutdown()


def test_a_joined_loop_never_runs_on_its_own_and_rates_must_agree(two_groups):
    pairs = batchsim.make_groups(two_groups, "cpu")
    for _, sim in pairs:
        sim.configure(), sim.activate()
    loops = _loops(pairs)
    with pytest.raises(RuntimeError, match="joined to another"):
        loops[1].run()
    other = SimLoop(pairs[1][1], control_rate=50)
    with pytest.raises(OptionError, match="one control rate: 100 Hz and 50 Hz"):
        SimLoop(pairs[0][1]).join(other)
    for _, sim in pairs:
        sim.shutdown()


def test_a_groups_worlds_draw_as_the_fleets_worlds_of_their_numbers(two_groups):
    """A world is numbered in the fleet: group yard's world 0 is the fleet's world 2, and draws as
    world 2 of any fleet of its robots does (`--world-offset 2`)."""
    randomize = {"seed": 5, "fields": [{"field": "body_mass", "scale": {"uniform": [0.5, 1.5]}}]}
    (_, _), (yard, y) = batchsim.make_groups(two_groups, "cpu", randomize=randomize)
    alone = batchsim.make(read_groups(two_groups).groups[1].fleet, 3, "cpu", randomize=randomize, world_offset=2)
    for sim in (y, alone):
        sim.configure()
    assert np.array_equal(y.world_params()["body_mass"], alone.world_params()["body_mass"])
    y.shutdown(), alone.shutdown()


def _batchsim(*args: str, timeout: float = 180) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "batchsim.cli", *args], capture_output=True, text=True, timeout=timeout)


def test_the_command_runs_a_fleet_of_groups_and_says_so(two_groups):
    done = _batchsim("--fleet", str(two_groups), "--no-ros", "--backend", "cpu", "--duration", "0.1", "--rtf", "0")
    assert done.returncode == 0, done.stderr
    first = next(line for line in done.stderr.splitlines() if not line.startswith("batchsim: warning"))
    assert first.startswith("batchsim: 5 worlds in 2 groups on cpu"), first
    assert "group arms: 2 x arms" in first and "group yard: 3 x yard" in first
    assert "stopped at sim time 0.100 s" in done.stderr


def test_worlds_beside_a_fleet_of_groups_is_one_line(two_groups):
    done = _batchsim("--fleet", str(two_groups), "--no-ros", "--worlds", "4")
    assert done.returncode == 2
    assert done.stderr.strip().splitlines()[-1] == (
        "batchsim: error: --worlds: a fleet of groups gives each group's worlds in its file (groups[k].worlds); drop --worlds"
    )


def test_info_lists_each_group_with_its_worlds_and_robots(two_groups):
    done = _batchsim("info", "--fleet", str(two_groups))
    assert done.returncode == 0, done.stderr
    out = done.stdout
    assert "5 worlds in 2 groups" in out
    assert "=== group arms: worlds 0..1 (2)" in out and "=== group yard: worlds 2..4 (3)" in out
    assert "rover/left_wheel_joint" in out
