"""A fleet's commands over its shards (batchsim/backends/sharded.py, fleet_rows.py), on CPU
devices: set_command of every world copies on as many threads as there are shards where
cores allow (fleet_rows.RowCopier), and the commands still reach every shard's worlds, a bad
row rejected for its world alone, as on one device. And a shard process says when it began
each request, on the fleet's clock (benchmarks/devices.py splits the fleet's wait with it)."""

from __future__ import annotations

import numpy as np
import pytest

import batchsim
from batchsim.backends import fleet_rows, sharded

SHARDS = pytest.mark.parametrize("processes", [False, True], ids=["threads", "processes"])
BAD = int(batchsim.Status.BAD_COMMAND)


@pytest.fixture
def copies_at_once(monkeypatch):
    """set_command's copy on threads, on this small host, for a few worlds' commands, a row a chunk."""
    monkeypatch.setattr(sharded, "copies_at_once", lambda nshard: True)
    monkeypatch.setattr(fleet_rows, "PARALLEL_COPY", 0)
    monkeypatch.setattr(fleet_rows.RowCopier, "CHUNK", 1)


def _active(sim: batchsim.BatchedSystem) -> batchsim.BatchedSystem:
    sim.configure()
    sim.activate()
    return sim


@SHARDS
def test_commands_set_at_once_reach_every_shards_worlds_and_bad_rows_stay_in_their_world(processes, copies_at_once):
    fleet = _active(batchsim.make("arm", 7, "warp", devices=["cpu"] * 3, processes=processes))
    one = _active(batchsim.make("arm", 7, "warp"))
    assert fleet.world_ranges == [range(0, 2), range(2, 5), range(5, 7)]
    assert fleet._copier is not None  # noqa: SLF001
    copied = []
    submit = fleet._copier.pool.submit  # noqa: SLF001
    fleet._copier.pool.submit = lambda *a: copied.append(a) or submit(*a)  # noqa: SLF001

    command = np.random.default_rng(1).uniform(-0.4, 0.4, fleet.command.shape)
    command[1, 2] = np.nan  # shard 0
    command[3, 0] = 1e12  # shard 1, beyond MAX_COMMAND
    command[6, 5] = -np.inf  # shard 2
    for sim in (fleet, one):
        sim.command = command
        assert sim.write() is batchsim.ReturnType.OK
    # seven chunks, taken by this thread and two of the pool's, one per shard beyond the first
    # (threads: the shards' own pool, which also ran their writes)
    assert sum(getattr(a[0], "__name__", "") == "run" for a in copied) == 2
    np.testing.assert_array_equal(fleet.command, command)
    assert fleet.status.tolist() == [0, BAD, 0, BAD, 0, 0, BAD] == one.status.tolist()
    for sim in (fleet, one):
        sim.step(20)
        sim.read()
    np.testing.assert_allclose(fleet.state, one.state, atol=1e-6)
    assert np.abs(fleet.state[4] - fleet.state[0]).max() > 1e-3  # the good worlds moved, each its own way

    # one row for every world (broadcast), then good commands again: BAD_COMMAND clears
    row = np.linspace(-0.2, 0.2, fleet.command.shape[1])
    fleet.command = row
    fleet.write()
    np.testing.assert_array_equal(fleet.command, np.tile(row, (7, 1)))
    assert not fleet.status.any()
    for sim in (fleet, one):
        sim.shutdown()


@SHARDS
def test_set_command_at_once_keeps_numpys_answer_for_a_view_of_itself_and_names_a_bad_shape(processes, copies_at_once):
    sim = _active(batchsim.make("arm", 4, "warp", devices=["cpu", "cpu"], processes=processes))
    sim.command = np.arange(24.0).reshape(4, 6)
    sim.command = sim.command[::-1]  # an overlap: NumPy's own copy, not rows at once
    np.testing.assert_array_equal(sim.command, np.arange(24.0).reshape(4, 6)[::-1])
    with pytest.raises(ValueError, match=r"command must have shape \(4, 6\) or \(6,\), got \(3, 6\)"):
        sim.command = np.zeros((3, 6))
    sim.set_command(np.full((2, 6), 0.1), worlds=[3, 0])  # listed worlds: as on one device
    assert sim.command[[0, 3]].tolist() == [[0.1] * 6] * 2
    sim.shutdown()


def test_a_hosts_few_cores_copy_commands_in_one_thread(monkeypatch):
    """Where the shards cannot poll (too few cores), nor does the fleet copy on threads."""
    monkeypatch.setattr(sharded, "spin_budget", lambda nshard: 0.0)
    assert not sharded.copies_at_once(2)
    sim = batchsim.make("arm", 4, "warp", devices=["cpu", "cpu"])
    assert sim._copier is None  # noqa: SLF001
    sim.shutdown()


def test_a_shard_process_says_when_it_began_each_request_on_the_fleets_clock():
    sim = _active(batchsim.make("arm", 4, "warp", devices=["cpu", "cpu"], processes=True))
    sim.command[:] = 0.1
    for call in (sim.write, lambda: sim.step(2), sim.read):
        call()
        for shard in sim.shards:
            assert shard.sent < shard.began <= shard.began + shard.busy <= shard.seen
            assert shard.busy > 0
    sim.shutdown()


def test_the_row_copier_copies_in_chunks_and_never_waits_for_a_thread_that_has_not_started():
    """Chunks go to whichever thread asks next, this one from the start: with every pool thread
    held up elsewhere the copy is done here, whole, and returns without them."""
    from concurrent.futures import ThreadPoolExecutor
    from threading import Event

    dst, src = np.zeros((1000, 21)), np.random.default_rng(2).uniform(-1, 1, (1000, 21))
    with ThreadPoolExecutor(2) as pool:
        copier = fleet_rows.RowCopier(pool, 2)
        copier.CHUNK = 21 * 8 * 7  # 7 rows a chunk: 143 chunks
        copier(dst, src)
        np.testing.assert_array_equal(dst, src)
        copier(dst, src[0])  # one row for every world
        np.testing.assert_array_equal(dst, np.tile(src[0], (1000, 1)))

        held = Event()
        for _ in range(2):
            pool.submit(held.wait, 30.0)
        copier(dst, src)
        np.testing.assert_array_equal(dst, src)
        held.set()
