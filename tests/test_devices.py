"""One fleet over several devices (batchsim/backends/sharded.py), on CPU devices.

The contract suite runs on the multi-device path too (conftest's `mjx-2dev`, `warp-2dev`);
these are the parts only a sharded system has.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

import batchsim
from batchsim.backends.sharded import split


def test_worlds_split_into_contiguous_ranges_larger_first():
    assert split(7, 3) == [range(0, 3), range(3, 5), range(5, 7)]
    assert split(4, 4) == [range(i, i + 1) for i in range(4)]
    with pytest.raises(ValueError, match="3 worlds cannot be split over 4 devices"):
        split(3, 4)


def test_a_fleet_on_two_devices_is_the_fleet_on_one():
    """Same commands, same physics: the sharded fleet's state equals the one-device fleet's,
    world for world, and a command to a world of the second device moves that world only."""
    fleets = [batchsim.make("arm", 5, "warp", devices=["cpu", "cpu"]), batchsim.make("arm", 5, "warp")]
    assert fleets[0].world_ranges == [range(0, 3), range(3, 5)]
    for sim in fleets:
        sim.configure()
        sim.activate()
        sim.command[4, 1] = 0.4  # world 4: the second device's second world
        for _ in range(5):
            sim.write()
            sim.step(10)
        sim.read()
    sharded, single = fleets
    np.testing.assert_array_equal(sharded.state, single.state)
    np.testing.assert_array_equal(sharded.time, single.time)
    moved = np.abs(sharded.state - sharded.state[0]).max(axis=1) > 1e-6
    assert moved.tolist() == [False, False, False, False, True]
    arrays = sharded.device_arrays()
    assert len(arrays["qpos"]) == 2 and np.asarray(arrays["qpos"][1]).shape == (2, sharded.model.nq)
    np.testing.assert_allclose(np.asarray(arrays["qpos"])[:, 1], sharded.state[:, 3], atol=1e-6)
    for sim in fleets:
        sim.shutdown()


def test_devices_are_for_the_device_backends():
    with pytest.raises(ValueError, match="cpu backend runs on the host's cores"):
        batchsim.make("arm", 4, "cpu", devices=[0, 1])
    with pytest.raises(ValueError, match="device 5 does not exist"):
        batchsim.make("arm", 4, "warp", devices=[5])


def test_a_shards_failed_world_is_named_and_held_by_its_fleet_number(tmp_path, caplog):
    """World 2 is the second device's world 0: the log line names world 2 of 3, and the fleet's
    arrays show its held readings while world 0 (the first device's) goes on."""
    from test_contract import UNSTABLE

    path = tmp_path / "unstable.xml"
    path.write_text(UNSTABLE)
    caplog.set_level(logging.WARNING, logger="batchsim")
    sim = batchsim.make(str(path), 3, "warp", devices=["cpu", "cpu"], deterministic=True)
    sim.configure()
    sim.activate()
    sim.command[:] = 0.0
    sim.write()
    sim.step(5)
    sim.read()
    before = sim.state.copy(), sim.time.copy()
    sim.command[2] = 1e9
    sim.write()
    sim.step(5)
    sim.step(5)
    sim.read()
    assert sim.status.tolist() == [0, 0, int(batchsim.Status.DIVERGED)]
    np.testing.assert_array_equal(sim.state[2], before[0][2])
    assert sim.time[2] == before[1][2] and sim.time.dtype == np.float64
    assert sim.time[0] > before[1][0]
    lines = [r.getMessage() for r in caplog.records if r.name.startswith("batchsim")]
    assert len(lines) == 1 and lines[0].startswith("batchsim: warp: world 2 diverged"), lines
    sim.reset([2])
    assert not sim.status.any()
    sim.shutdown()
