"""The messages between a fleet and a shard process (batchsim/backends/sharded/messages.py),
both ends in one process on two threads: a control period's operations go through the
control row alone, anything else on the socket, and a sleeping side is woken."""

from __future__ import annotations

import logging
import socket
import threading
from multiprocessing.connection import Connection

import numpy as np
import pytest

from batchsim.backends.sharded.messages import Bell, FleetEnd, ShardEnd, control_array
from batchsim.backends.sharded.shards import PERIOD_OPS, ShardOp
from batchsim.memory import Layout, Memory


@pytest.fixture(params=[0.0, 0.05], ids=["sleeping", "polling"])
def ends(request):
    memory = Memory.create(Layout([control_array(2)]), shared=False)
    ours, theirs = socket.socketpair()
    to_shard, to_fleet = Bell.pair(), Bell.pair()
    fleet_conn, shard_conn = Connection(ours.detach()), Connection(theirs.detach())
    fleet = FleetEnd(memory["control"][1], fleet_conn, to_fleet, to_shard, PERIOD_OPS, request.param)
    shard = ShardEnd(memory["control"][1], shard_conn, to_shard, to_fleet, PERIOD_OPS, request.param)
    yield fleet, shard
    for conn in (fleet_conn, shard_conn):
        conn.close()
    to_shard.close()
    to_fleet.close()
    memory.close()


def _serve(shard: ShardEnd, answers: list, seen: list) -> threading.Thread:
    """A shard that answers each request with the next of `answers` (ok, value, records)."""

    def run() -> None:
        for ok, value, records in answers:
            request = None
            while request is None:
                request = shard.next(5.0)
            seen.append(request)
            shard.answer(ok, value, 3, records, 0.25)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_a_periods_operations_go_through_the_control_row_alone(ends, monkeypatch):
    fleet, shard = ends
    seen: list = []
    thread = _serve(shard, [(True, None, [])] * 4, seen)

    def no_socket(*args, **kwargs):
        raise AssertionError("the socket was used")

    for conn in (fleet.conn, shard.conn):
        monkeypatch.setattr(conn, "send", no_socket)
        monkeypatch.setattr(conn, "recv", no_socket)
    requests = [
        (ShardOp.WRITE, (1.5, 0.01)),
        (ShardOp.STEP, (10,)),
        (ShardOp.READ, (None, None)),
        (ShardOp.READ, ()),
    ]
    for op, args in requests:
        fleet.send(op, args, {})
        assert fleet.answered(5.0)
        assert fleet.reply() == (True, None, 3, [], 0.25)
    thread.join(5.0)
    assert seen == [(op, args, {}) for op, args in requests]
    assert isinstance(seen[1][1][0], int) and isinstance(seen[0][1][0], float)


def test_anything_else_goes_on_the_socket_large_or_not(ends):
    """Other operations, arguments beyond numbers, a value, log lines and failures are
    pickled; a 16 MB request and reply pass without either side blocking the other."""
    fleet, shard = ends
    big = np.arange(2 * 1024 * 1024, dtype=np.float64)
    failure = ValueError("world 3 is frozen")
    records = [("batchsim", logging.WARNING, "batchsim: warp: world 2 diverged")]
    answers = [(True, big, []), (True, None, records), (False, failure, []), (True, None, [])]
    seen: list = []
    thread = _serve(shard, answers, seen)
    fleet.send(ShardOp.SET_QSTATE, (np.array([1]), big, big), {})
    assert fleet.answered(5.0)
    ok, value, _, _, _ = fleet.reply()
    assert ok and np.array_equal(value, big)
    fleet.send(ShardOp.STEP, (10,), {})  # a period's operation whose answer has log lines
    assert fleet.answered(5.0) and fleet.reply()[3] == records
    fleet.send(ShardOp.WRITE, (1.0, 0.01), {})
    assert fleet.answered(5.0)
    ok, value, _, _, _ = fleet.reply()
    assert not ok and isinstance(value, ValueError) and str(value) == "world 3 is frozen"
    fleet.send(ShardOp.READ, (), {"time": 1.0})  # keyword arguments: pickled
    assert fleet.answered(5.0) and fleet.reply()[0]
    thread.join(5.0)
    assert seen[0][0] is ShardOp.SET_QSTATE and np.array_equal(seen[0][1][1], big)
    assert seen[3] == (ShardOp.READ, (), {"time": 1.0})


def test_a_closed_fleet_ends_the_shards_wait():
    memory = Memory.create(Layout([control_array(1)]), shared=False)
    ours, theirs = socket.socketpair()
    bell = Bell.pair()
    shard = ShardEnd(memory["control"][0], Connection(theirs.detach()), bell, Bell.pair(), PERIOD_OPS, 0.0)
    assert shard.next(0.05) is None  # nothing asked: a timeout, not an end
    ours.close()
    with pytest.raises(EOFError):
        shard.next(5.0)


def test_the_shards_beginning_of_a_request_comes_back_in_the_row(ends):
    """When the shard began a request (its perf_counter, one clock on Linux) comes back beside
    its busy time, for the fleet to split its wait (benchmarks/devices.py)."""
    fleet, shard = ends
    fleet.send(ShardOp.STEP, (10,), {})
    assert shard.next(5.0) == (ShardOp.STEP, (10,), {})
    shard.answer(True, None, 3, [], 0.25, 12.5)
    assert fleet.answered(5.0)
    assert fleet.reply() == (True, None, 3, [], 0.25) and fleet.began() == 12.5
