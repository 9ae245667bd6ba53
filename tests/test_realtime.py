"""The loop thread's real-time scheduling (batchsim/loop/realtime.py), as controller_manager sets its own:
SCHED_FIFO while it paces a real-time factor, from its second period on, never for the threads
it starts, given up when it falls behind, and back to what it was when run() returns."""

from __future__ import annotations

import gc
import logging
import os
import re
import signal
import threading
import time

import pytest

import batchsim
from batchsim.loop import SimLoop, realtime

pytestmark = [
    pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="Linux scheduling"),
    # alone (the Makefile's second pass): beside the other test process on 2 cores, a period
    # fell 0.5 s behind and the loop gave SCHED_FIFO up, as it should (a CI run)
    pytest.mark.timing,
]


def _can_elevate() -> bool:
    """Whether this user may ask for SCHED_FIFO (root, CAP_SYS_NICE or an rtprio limit)."""
    result = []

    def probe() -> None:
        saved, problems = realtime.elevate(1)
        result.append(not problems)
        realtime.restore(saved)

    t = threading.Thread(target=probe)
    t.start()
    t.join()
    return result[0]


class Recorder:
    """A participant that notes the loop thread's scheduling each period, and can stall."""

    def __init__(self, stall_at: int = -1, stall: float = 0.0, spawn_at: int = -1):
        self.seen: list[tuple[int, int]] = []
        self.stall_at, self.stall, self.spawn_at = stall_at, stall, spawn_at
        self.spawned: list[tuple[int, int]] = []
        self.frozen: list[int] = []  # gc.get_freeze_count() each period
        self.cpus: list[set[int]] = []  # the loop thread's cores each period

    def update(self, sim, time_, period) -> None:
        k = len(self.seen)
        self.seen.append(realtime.current())
        self.cpus.append(os.sched_getaffinity(0))
        self.frozen.append(gc.get_freeze_count())
        if k == self.spawn_at:  # a thread the loop thread starts keeps the normal policy
            t = threading.Thread(target=lambda: self.spawned.append(realtime.current()))
            t.start()
            t.join()
        if k == self.stall_at:
            time.sleep(self.stall)


def run_loop(rtf: float, priority: int, periods: int, recorder: Recorder, affinity=()) -> tuple[SimLoop, list]:
    sim = batchsim.make("arm", 2, "cpu")
    sim.configure()
    sim.activate()
    loop = SimLoop(sim, rtf=rtf, duration=periods * 0.01, participants=[recorder], thread_priority=priority, cpu_affinity=affinity)
    after: list = []

    def body() -> None:  # a thread of its own, so the test's thread is never touched
        loop.run()
        after.append((realtime.current(), os.sched_getaffinity(0)))

    t = threading.Thread(target=body)
    t.start()
    t.join(timeout=60)
    sim.shutdown()
    return loop, after


NORMAL = (os.SCHED_OTHER, 0)


@pytest.mark.skipif(not _can_elevate(), reason="this user may not ask for SCHED_FIFO (see the warning test)")
def test_a_paced_loop_runs_sched_fifo_on_its_cores_from_its_second_period_and_restores_them():
    rec = Recorder()  # rtf 0.05: 200 ms a period, so a loaded machine never puts it 0.5 s behind
    _, after = run_loop(rtf=0.05, priority=50, periods=6, recorder=rec, affinity=(0,))
    assert rec.seen[0] == NORMAL and rec.cpus[0] == set(range(os.cpu_count()))  # the first period may compile
    assert [policy & ~os.SCHED_RESET_ON_FORK for policy, _ in rec.seen[1:]] == [os.SCHED_FIFO] * 5
    assert {p for _, p in rec.seen[1:]} == {50} and all(c == {0} for c in rec.cpus[1:])
    (policy, affinity) = after[0]
    assert policy == NORMAL and affinity == set(range(os.cpu_count()))


@pytest.mark.skipif(not _can_elevate(), reason="this user may not ask for SCHED_FIFO")
def test_the_threads_a_sched_fifo_loop_starts_keep_the_normal_policy():
    rec = Recorder(spawn_at=2)
    run_loop(rtf=0.05, priority=50, periods=4, recorder=rec)
    assert rec.seen[2][0] & ~os.SCHED_RESET_ON_FORK == os.SCHED_FIFO
    assert rec.spawned == [NORMAL]  # SCHED_RESET_ON_FORK: its threads and processes don't inherit it


def test_a_paced_loop_freezes_start_up_out_of_the_collector_and_thaws_it_after():
    """A full collection of a big fleet's start-up objects cost one period 160-190 ms (1024 arms
    with the bridge on an H100 host): from the second period on they are frozen."""
    gc.unfreeze()
    rec = Recorder()
    run_loop(rtf=1.0, priority=0, periods=4, recorder=rec, affinity=tuple(sorted(os.sched_getaffinity(0))))
    assert rec.frozen[0] == 0 and all(n > 0 for n in rec.frozen[1:])
    assert gc.get_freeze_count() == 0


@pytest.mark.skipif(not _can_elevate(), reason="this user may not ask for SCHED_FIFO")
def test_a_loop_that_falls_behind_gives_sched_fifo_up_and_says_so(caplog):
    rec = Recorder(stall_at=3, stall=1.2)  # rtf 0.05: only the stall puts it 0.5 s behind
    with caplog.at_level(logging.WARNING, logger="batchsim"):
        run_loop(rtf=0.05, priority=50, periods=6, recorder=rec)
    assert rec.seen[3][0] & ~os.SCHED_RESET_ON_FORK == os.SCHED_FIFO
    assert rec.seen[5] == NORMAL
    lines = [r.getMessage() for r in caplog.records if "gives up SCHED_FIFO" in r.getMessage()]
    assert len(lines) == 1 and re.search(r"the loop fell \d+\.\d s behind rtf 0.05: its thread gives up", lines[0]), lines


@pytest.mark.skipif(not _can_elevate(), reason="this user may not ask for SCHED_FIFO")
def test_a_loop_that_kept_up_again_asks_for_sched_fifo_again(caplog, monkeypatch):
    """After one stall the loop stayed at the normal policy for the rest of the run, and on a
    shared host at RTF 0.27-0.31 (issue 46): it asks again once it has kept up for RETRY s."""
    monkeypatch.setattr(realtime, "RETRY", 0.3)
    rec = Recorder(stall_at=3, stall=1.2)
    with caplog.at_level(logging.WARNING, logger="batchsim"):
        run_loop(rtf=0.05, priority=50, periods=12, recorder=rec)
    fifo = [p & ~os.SCHED_RESET_ON_FORK == os.SCHED_FIFO for p, _ in rec.seen]
    assert fifo[3] and not fifo[5] and fifo[-1], fifo  # given up after the stall, asked for again
    lines = [r.getMessage() for r in caplog.records if "gives up SCHED_FIFO" in r.getMessage()]
    assert len(lines) == 1 and "then asks again" in lines[0], lines


def test_a_loop_run_flat_out_or_asked_for_nothing_keeps_the_normal_policy():
    for rtf, priority in ((0.0, 50), (1.0, 0)):
        rec = Recorder()
        run_loop(rtf=rtf, priority=priority, periods=4, recorder=rec)
        assert set(rec.seen) == {NORMAL}, (rtf, priority)


def test_a_loop_run_flat_out_keeps_its_cores_but_never_asks_for_sched_fifo():
    """--cpu-affinity was dropped at --rtf 0: a flat-out fleet's loop shared its core with the
    bridge workers and subscribers (1024 arms with ROS at 0.928 of without on an H100 host)."""
    rec = Recorder()
    core = min(os.sched_getaffinity(0))
    _, after = run_loop(rtf=0.0, priority=50, periods=4, recorder=rec, affinity=(core,))
    assert set(rec.seen) == {NORMAL}
    assert all(c == {core} for c in rec.cpus[1:])  # from the second period on, as when paced
    assert after[0][1] == set(range(os.cpu_count()))


def test_without_permission_the_loop_runs_and_says_why_once(monkeypatch, caplog):
    def refuse(*args):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    rec = Recorder()
    with caplog.at_level(logging.WARNING, logger="batchsim"):
        loop, _ = run_loop(rtf=1.0, priority=50, periods=5, recorder=rec)
    assert loop.sim_time == pytest.approx(0.05)
    lines = [r.getMessage() for r in caplog.records if "SCHED_FIFO" in r.getMessage()]
    assert len(lines) == 1, lines
    assert "without SCHED_FIFO priority 50: Operation not permitted" in lines[0] and "rtprio" in lines[0]


@pytest.mark.ros
@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="needs a core to keep free")
def test_a_pinned_loop_keeps_its_bridge_workers_off_its_core(tmp_path):
    """--cpu-affinity 0: the loop thread runs on core 0 and no bridge worker does (a woken
    worker would take the loop's core), as the command line a user types starts it."""
    from conftest import need

    need("rclpy")
    import subprocess
    import sys

    from ros_fleet import LOCALHOST, bridge_workers, domain_id, release_domain

    domain = domain_id(60)
    env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(domain), "PYTHONUNBUFFERED": "1"}
    argv = [sys.executable, "-m", "batchsim.cli", "--worlds", "4", "--bridge-workers", "2", "--cpu-affinity", "0", "--quiet"]
    proc = subprocess.Popen(argv, env=env, stderr=subprocess.PIPE, text=True)
    try:
        for line in proc.stderr:  # the start line comes once every worker serves
            if " x arm on " in line:
                break
        time.sleep(0.5)  # the loop's second period pins it
        workers = bridge_workers(proc.pid)
        assert len(workers) == 2
        for pid in workers.values():
            assert 0 not in os.sched_getaffinity(pid)
        assert os.sched_getaffinity(proc.pid) == {0}  # the loop runs in the main thread
        os.kill(workers[1], signal.SIGKILL)  # restarted from the loop's (pinned) thread: still off it
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and bridge_workers(proc.pid).get(1, workers[1]) == workers[1]:
            time.sleep(0.1)
        restarted = bridge_workers(proc.pid)[1]
        assert restarted != workers[1] and 0 not in os.sched_getaffinity(restarted)
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        release_domain(domain)


def test_cpu_affinity_names_only_cores_this_process_may_run_on(monkeypatch):
    """A container's cpuset can be fewer cores than os.cpu_count(): a core outside it is one
    line naming the cores that are there, not a warning from the kernel at the second period."""
    from batchsim.loop import OptionError

    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 2})
    sim = batchsim.make("arm", 1, "cpu")
    with pytest.raises(OptionError, match=r"names no core of this machine that this process may run on \(0,2\): 1"):
        SimLoop(sim, cpu_affinity=(1,))
    SimLoop(sim, cpu_affinity=(2,))
    sim.shutdown()


def test_the_cores_kept_for_the_loop_include_their_hardware_threads(tmp_path):
    """A bridge worker on the loop core's SMT sibling shares its execution units and caches:
    --cpu-affinity keeps the workers (and fleet.py's subscribers) off the siblings too."""
    from batchsim.loop.realtime import with_siblings

    for cpu, siblings in ((0, "0,8"), (8, "0,8"), (1, "1-2"), (3, "3")):
        (tmp_path / f"cpu{cpu}" / "topology").mkdir(parents=True)
        (tmp_path / f"cpu{cpu}" / "topology" / "thread_siblings_list").write_text(siblings + "\n")
    assert with_siblings((0,), str(tmp_path)) == {0, 8}
    assert with_siblings((1, 3), str(tmp_path)) == {1, 2, 3}
    assert with_siblings((5,), str(tmp_path)) == {5}  # sysfs silent: the core alone
    assert with_siblings((), str(tmp_path)) == frozenset()
