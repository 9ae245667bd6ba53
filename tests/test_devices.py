"""One fleet over several devices (batchsim/backends/sharded/system.py), on CPU devices.

The contract suite runs on the multi-device path too (conftest's `mjx-2dev`, `warp-2dev`);
these are the parts only a sharded system has, with its shards in threads and in processes
of their own (`processes=True`, batchsim/backends/sharded/shards.py).
"""

from __future__ import annotations

import gc
import logging
import os
import pickle
import signal
import time
from pathlib import Path

import numpy as np
import pytest

import batchsim
from batchsim.backends.sharded.shards import CALLS, ShardOp, ShardProcessError, serve
from batchsim.hardware import BatchedSystem
from batchsim.loop import OptionError
from batchsim.types import split_worlds

SHARDS = pytest.mark.parametrize("processes", [False, True], ids=["threads", "processes"])


def test_worlds_split_into_contiguous_ranges_as_even_as_can_be():
    """One split for devices and bridge workers alike (issue 22): range i ends at world
    round(nworld * (i + 1) / parts), halves up (7 over 3 was 3, 2, 2 here, 2, 3, 2 for workers)."""
    assert split_worlds(7, 3) == [range(0, 2), range(2, 5), range(5, 7)]
    assert split_worlds(5, 2) == [range(0, 3), range(3, 5)]
    assert split_worlds(4, 4) == [range(i, i + 1) for i in range(4)]
    with pytest.raises(ValueError, match="3 worlds cannot be split into 4 ranges"):
        split_worlds(3, 4)
    with pytest.raises(OptionError, match="3 worlds cannot be split over 4 devices"):
        batchsim.make("arm", 3, "warp", devices=["cpu"] * 4)


def test_shard_operations_are_enum_members_that_survive_the_socket():
    """What the fleet asks of a shard is a ShardOp (issue 22), pickled as it is to a shard
    process; those run as calls name a system's method; a string is no operation."""
    assert all(pickle.loads(pickle.dumps(op)) is op for op in ShardOp)
    assert all(callable(getattr(BatchedSystem, op.value)) for op in CALLS)
    assert ShardOp.STEP not in CALLS and ShardOp.DEVICE_ARRAYS not in CALLS
    with pytest.raises(ValueError, match="a shard serves no operation 'step'"):
        serve(None, None, "step", (), {})


@SHARDS
def test_a_fleet_on_two_devices_is_the_fleet_on_one(processes):
    """Same commands, same physics: the sharded fleet's state equals the one-device fleet's,
    world for world, and a command to a world of the second device moves that world only."""
    fleets = [
        batchsim.make("arm", 5, "warp", devices=["cpu", "cpu"], processes=processes),
        batchsim.make("arm", 5, "warp"),
    ]
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


@SHARDS
def test_a_shard_reads_into_the_fleets_arrays_and_a_reset_keeps_other_commands(processes):
    """A shard's system reads into its rows of the fleet's arrays and takes its commands from
    them (share_host_arrays: no copy between them). So a reset of one world sets that world's
    command back and leaves a command set but not yet written in another world of the same
    shard as it is, as one device does (the shard's copy of its commands overwrote it before)."""
    fleets = [
        batchsim.make("arm", 4, "warp", devices=["cpu", "cpu"], processes=processes),
        batchsim.make("arm", 4, "warp"),
    ]
    if not processes:
        shard = fleets[0].shards[1].system
        assert np.shares_memory(shard.readings, fleets[0].readings)
        assert np.shares_memory(shard.command, fleets[0].command)
    for sim in fleets:
        sim.configure()
        sim.activate()
        sim.command[:] = 0.2
        sim.write()
        sim.command[1] = 0.3  # world 1: the first shard's, beside the world reset
        sim.reset([0])
    np.testing.assert_array_equal(fleets[0].command, fleets[1].command)
    assert fleets[0].command[1].tolist() == [0.3] * fleets[0].command.shape[1]
    for sim in fleets:
        sim.write()
        sim.step(5)
        sim.read()
    np.testing.assert_array_equal(fleets[0].state, fleets[1].state)
    for sim in fleets:
        sim.shutdown()


@SHARDS
def test_every_worlds_body_poses_come_through_the_fleets_rows_as_any_worlds_do(processes):
    """Every world's body poses (tf's, each period) go through the fleet's rows (ShardOp.POSES,
    nothing pickled), some worlds' through the shards' answers: both as one device gives them,
    arrays of the caller's own."""
    fleets = [
        batchsim.make("arm", 5, "warp", devices=["cpu", "cpu"], processes=processes),
        batchsim.make("arm", 5, "warp"),
    ]
    for sim in fleets:
        sim.configure()
        sim.activate()
        sim.command[4, 1] = 0.4
        sim.write()
        sim.step(20)
    (every, one), some = [sim.body_poses() for sim in fleets], [sim.body_poses([4, 0, 3]) for sim in fleets]
    for a, b in (*zip(every, one, strict=True), *zip(*some, strict=True)):
        np.testing.assert_allclose(a, b, atol=1e-6)
    assert np.abs(every[0][4] - every[0][0]).max() > 1e-3  # world 4 moved, on the second device
    every[0][:] = 0.0  # the caller's own: the next call is not changed by it
    np.testing.assert_allclose(fleets[0].body_poses()[0], one[0], atol=1e-6)
    for sim in fleets:
        sim.shutdown()


@SHARDS
def test_tfs_poses_come_with_the_periods_read_and_are_fetched_again_after_a_reset(processes):
    """Issue 27: tf copies every world's poses each period; once it has, each read brings them
    along (ShardOp.READ_POSES), so the copy waits for no shard. Anything else sent to the shards
    between the read and the copy (a reset here) has them fetched again: never stale."""
    sim = batchsim.make("arm", 4, "warp", devices=["cpu", "cpu"], processes=processes)
    sim.configure()
    sim.activate()
    sent: list[ShardOp] = []
    for shard in sim.shards:
        for name in ("submit", "call"):
            method = getattr(shard, name)
            setattr(shard, name, lambda op, *a, _m=method, **k: (sent.append(op), _m(op, *a, **k))[1])
    out = np.zeros((4, sim.model.nbody, 7))

    def tf_copy() -> None:  # as tf's channel fill copies them, checked against the shards' answers
        sim.body_poses_into(out[..., :3], out[..., 3:])
        xpos, xquat = sim.body_poses([0, 1, 2, 3])  # pickled through each shard's own body_poses
        np.testing.assert_array_equal(out[..., :3], xpos)
        np.testing.assert_array_equal(out[..., 3:], xquat)

    try:
        for period in range(4):
            sim.read()
            if period == 3:
                sim.reset([1])
            del sent[:]
            tf_copy()
            assert sent.count(ShardOp.POSES) == (2 if period in (0, 3) else 0)  # the first, and after the reset
            sim.command[1:] = 0.3 * (period + 1)
            sim.write()
            sim.step(5)
        sent.clear()
        sim.read()
        assert sent == [ShardOp.READ_POSES] * 2
        sim.read()  # no copy since the last read: the poses stay with the shards
        assert sent[2:] == [ShardOp.READ] * 2
    finally:
        sim.shutdown()


def test_devices_are_for_the_device_backends():
    with pytest.raises(ValueError, match="cpu backend runs on the host's cores"):
        batchsim.make("arm", 4, "cpu", devices=[0, 1])
    with pytest.raises(ValueError, match="device 5 does not exist"):
        batchsim.make("arm", 4, "warp", devices=[5])
    with pytest.raises(ValueError, match="device 'cuda:3' does not exist: the warp backend has"):
        batchsim.make("arm", 4, "warp", devices=["cpu", "cuda:3"], processes=True)
    with pytest.raises(ValueError, match="processes=True is for a fleet over several devices"):
        batchsim.make("arm", 4, "warp", processes=True)


@SHARDS
def test_a_shards_failed_world_is_named_and_held_by_its_fleet_number(tmp_path, caplog, processes):
    """World 2 is the second device's world 0: the log line names world 2 of 3 (logged in
    the fleet's process, also when the shard runs in its own), and the fleet's arrays show
    its held readings while world 0 (the first device's) goes on."""
    from test_contract import UNSTABLE

    path = tmp_path / "unstable.xml"
    path.write_text(UNSTABLE)
    caplog.set_level(logging.WARNING, logger="batchsim")
    sim = batchsim.make(str(path), 3, "warp", devices=["cpu", "cpu"], deterministic=True, processes=processes)
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


# ---------------------------------------------------------------- shards in processes


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie is gone for our purposes (its parent reaps it at the next wait)
    stat = Path(f"/proc/{pid}/stat")
    return not (stat.exists() and stat.read_text().split(")")[-1].split()[0] == "Z")


def _segments() -> set[str]:
    return {p.name for p in Path("/dev/shm").glob(f"batchsim_{os.getpid()}_*")}


def _gone(pids: list[int], timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not any(_alive(pid) for pid in pids):
            return True
        time.sleep(0.05)
    return False


def test_shard_processes_share_the_fleets_arrays_and_end_with_it():
    """The shards run in processes of their own; the fleet's arrays are in shared memory
    they write; device_arrays() are host copies of theirs; shutdown() ends the processes and
    removes the segment, and so does a fleet dropped without shutdown()."""
    before = _segments()
    sim = batchsim.make("arm", 5, "warp", devices=["cpu", "cpu"], processes=True)
    pids = [shard.pid for shard in sim.shards]
    assert len(set(pids)) == 2 and os.getpid() not in pids and all(_alive(p) for p in pids)
    assert len(_segments() - before) == 1
    sim.configure()
    sim.activate()
    sim.command[:] = 0.3
    sim.write()
    sim.step(20)
    sim.read()
    names = sim.export_state_interfaces()
    pos = sim.state[:, [names.index(f"joint{i}/position") for i in range(1, 7)]]
    arrays = sim.device_arrays()
    assert [np.asarray(a).shape[0] for a in arrays["qpos"]] == [3, 2]
    np.testing.assert_allclose(np.asarray(arrays["qpos"]), pos, atol=1e-6)
    sim.shutdown()
    assert _gone(pids) and _segments() == before

    dropped = batchsim.make("arm", 4, "warp", devices=["cpu", "cpu"], processes=True)
    pids = [shard.pid for shard in dropped.shards]
    del dropped
    gc.collect()
    assert _gone(pids) and _segments() == before


def test_a_killed_shard_process_is_one_error_naming_its_device_and_worlds():
    sim = batchsim.make("arm", 4, "warp", devices=["cpu", "cpu"], processes=True)
    sim.configure()
    sim.activate()
    sim.step(1)
    os.kill(sim.shards[1].pid, signal.SIGKILL)
    with pytest.raises(ShardProcessError, match=r"shard process of cpu \(worlds 2\.\.3, pid \d+\) exited with code -9"):
        sim.step(1)
    sim.shutdown()  # the other shard still stops cleanly
    assert _gone([shard.pid for shard in sim.shards])


def test_a_bad_command_in_one_shard_process_marks_that_world_only():
    """The shard process checks its rows as one system does: BAD_COMMAND on world 3 (the
    second device's), the rest applied; the next good command clears it."""
    sim = batchsim.make("arm", 4, "warp", devices=["cpu", "cpu"], processes=True)
    sim.configure()
    sim.activate()
    sim.command[:] = 0.2
    sim.command[3, 0] = np.nan
    sim.write()
    assert sim.status.tolist() == [0, 0, 0, int(batchsim.Status.BAD_COMMAND)]
    sim.command[3, 0] = 0.2
    sim.write()
    assert not sim.status.any()
    sim.shutdown()


def test_a_waiting_side_polls_only_where_there_are_cores_to_spare(monkeypatch):
    """The fleet and its shard processes poll for messages (no wake-up latency) only where
    each polling process leaves a core to spare; a fleet that polls works as one that sleeps."""
    from batchsim.backends.sharded import shards

    monkeypatch.setattr(shards.os, "sched_getaffinity", lambda pid: set(range(5)))
    assert shards.spin_budget(2) == 0.0  # 3 polling processes need 6 cores
    monkeypatch.setattr(shards.os, "sched_getaffinity", lambda pid: set(range(6)))
    assert shards.spin_budget(2) == shards.SPIN
    sim = batchsim.make("arm", 4, "warp", devices=["cpu", "cpu"], processes=True)
    assert [shard.spin for shard in sim.shards] == [shards.SPIN] * 2
    sim.configure()
    sim.activate()
    sim.command[:] = 0.2
    for _ in range(3):
        sim.write()
        sim.step(5)
    sim.read()
    assert sim.time == pytest.approx(np.full(4, 15 * sim.dt))
    sim.shutdown()


def test_mjx_shards_in_processes_run_the_fleet_of_one_device():
    """mjx's shard processes on JAX's two CPU devices (conftest makes two): the same physics as
    one device, to float32 rounding."""
    fleets = [
        batchsim.make("arm", 4, "mjx", devices=["cpu:0", "cpu:1"], processes=True),
        batchsim.make("arm", 4, "mjx"),
    ]
    for sim in fleets:
        sim.configure()
        sim.activate()
        sim.command[3, 1] = 0.3
        for _ in range(5):
            sim.write()
            sim.step(10)
        sim.read()
    np.testing.assert_allclose(fleets[0].state, fleets[1].state, atol=1e-5)
    assert np.abs(fleets[0].state[3] - fleets[0].state[0]).max() > 1e-3  # world 3 moved, on device 1
    for sim in fleets:
        sim.shutdown()
