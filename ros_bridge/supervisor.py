"""The bridge's workers: started, woken, watched and restarted. No rclpy here (in process
mode; with `--bridge-workers 0` the one worker runs in this process).

Worker 0 starts first: it checks the ROS graph for another fleet serving these worlds or
/clock. A worker that dies is noticed within SUPERVISE seconds, the log names its worlds,
and it is restarted on the same shared memory (its counters continue, so nothing is
replayed); one that dies again soon after is restarted with a back-off. A worker that
stops answering (its tick counter stands still: stopped, deadlocked; protocol/liveness.py) is
noticed after HUNG_AFTER seconds, logged naming its worlds and shown in the other workers'
/diagnostics, and killed and restarted if it has not come back after
HUNG_RESTART seconds. A worker that is merely slow still ticks, and is left alone.
"""

from __future__ import annotations

import os
import pickle
import select
import subprocess
import sys
import time as wallclock
from pathlib import Path
from typing import Any

from batchsim.memory import Memory
from ros_bridge.naming import worlds_label
from ros_bridge.plan import FleetPlan
from ros_bridge.protocol import liveness
from ros_bridge.registry import ConflictKind, Registry
from ros_bridge.throttle import LogThrottle
from ros_bridge.transport import PROFILES_FILE, TransportProfile

SUPERVISE = 0.25  # s of wall time between two looks at the workers
HUNG_AFTER = 1.0  # s without a tick before a worker is reported as not answering (it ticks every 0.1 s at least)
# s without a tick before it is killed and restarted: long, since a worker can be busy for seconds
# without being hung (a graph scan while thousands of endpoints are discovered, on a GPU host)
HUNG_RESTART = 30.0
START_TIMEOUT = 120.0  # s a worker may take to come up (imports, endpoints, the start-up check)
START_WORLDS = 2048  # worlds a worker creates the endpoints of well within START_TIMEOUT


def start_timeout(nworld: int) -> float:
    """Seconds a worker serving `nworld` worlds may take to come up. Creating endpoints grows
    faster than the worlds (one worker on the 2-core VM: 6.5 s for 1024 worlds, 20.6 s for 2048,
    104 s for 4096, idle; over 120 s under load): START_TIMEOUT up to START_WORLDS, then with
    the square of the worlds."""
    return START_TIMEOUT * max(1.0, (nworld / START_WORLDS) ** 2)
STOP_TIMEOUT = 1.5  # s workers get to leave the ROS graph before they are killed

# the workers' rclpy log lines (`batchsim: WARN [batchsim_0_1]: ...`), beside batchsim's
# `batchsim: warning: ...`; a RCUTILS_CONSOLE_OUTPUT_FORMAT of the user's own wins
LOG_FORMAT = "batchsim: {severity} [{name}]: {message}"


class FleetConflict(ValueError):
    """Another process on the ROS domain already serves these worlds, or /clock.

    Attributes:
      kind: what it already serves; given as a string where a worker reported it.
    """

    def __init__(self, kind: ConflictKind | str, message: str):
        super().__init__(message)
        self.kind = ConflictKind(kind)


class WorkerError(RuntimeError):
    """A bridge worker failed to start."""


class _Process:
    """One worker process and its pipes."""

    def __init__(self, index: int, popen: subprocess.Popen, wake: int, status: int):
        self.index = index
        self.popen = popen
        self.wake = wake  # write end: a byte per period
        self.status = status  # read end: "ready", "conflict ...", "error ..."
        self.ready = False
        self.restarts = 0
        self.died_at = 0.0
        self.beat = -1  # its tick counter at the last look, and when it last moved
        self.beat_at = wallclock.monotonic()
        self.hung_since = 0.0

    def close_pipes(self) -> None:
        for fd in (self.wake, self.status):
            try:
                os.close(fd)
            except OSError:
                pass
        self.wake = self.status = -1


class Supervisor:
    """The workers of `plan` over `memory`: processes (`processes`), or one in this process.

    Attributes:
      worker: the in-process worker, or None.
      notify_r, notify_w: the pipe workers write a byte to when a command arrives (lockstep).
    """

    def __init__(
        self,
        plan: FleetPlan,
        memory: Memory,
        *,
        processes: bool,
        throttle: LogThrottle,
        command_timeout: float | None,
        avoid_cpus: frozenset[int] = frozenset(),
    ):
        self.plan = plan
        # the workers' cores, taken now: a worker restarted from the (pinned) loop thread would inherit its
        self._cpus = frozenset(os.sched_getaffinity(0)) - avoid_cpus if avoid_cpus else frozenset()
        self.memory = memory
        self.processes = processes
        self.throttle = throttle
        self.command_timeout = command_timeout
        self._procs: list[_Process] = []
        self.worker: Any = None
        self.registry = Registry.for_domain()
        # Fast DDS's shared-memory segment sized for the cameras' and lidars' messages
        self.transport = TransportProfile(plan.sensors, [hi - lo for lo, hi in plan.ranges], plan.control_rate)
        self._environ_before: str | None = None
        self.notify_r, self.notify_w = os.pipe()
        os.set_blocking(self.notify_r, False)
        os.set_blocking(self.notify_w, False)
        self._next_supervise = 0.0
        self.watchers: list[Any] = []  # other helpers' checks, called by supervise()
        self._closed = False

    def start(self) -> None:
        """Bring the workers up (worker 0 first: it checks the graph for another fleet).
        FleetConflict or WorkerError if they cannot serve (then every one started is stopped)."""
        try:
            conflict = self.registry.claim(self.plan.node_names[0], self.plan.namespaces, self.plan.clock)
            if conflict is not None:
                raise FleetConflict(*conflict)
            if self.processes:
                first = self._spawn(0, check=True)
                self._procs.append(first)
                self._await_ready([first])
                for j in range(1, self.plan.nworker):
                    self._procs.append(self._spawn(j, check=False))  # appended at once: close() stops it
                self._await_ready(self._procs[1:])
            else:
                from ros_bridge.worker import Worker  # rclpy comes in only here

                self._environ_before = os.environ.get(PROFILES_FILE)
                self.transport.apply(os.environ)  # read when this process's first participant is made

                self.worker = Worker(self.plan, 0, self.memory, notify_fd=self.notify_w if self.plan.lockstep else None)
                conflict = self.worker.check_conflicts()
                if conflict is not None:
                    raise FleetConflict(*conflict)
                self.worker.build()
                self.worker.start()
        except BaseException:
            self.close()
            raise

    @property
    def pids(self) -> list[int]:
        """The worker processes' ids (empty when the bridge runs in this process)."""
        return [p.popen.pid for p in self._procs if p.popen.poll() is None]

    def close(self) -> None:
        """Stop every worker (they leave the ROS graph; killed after STOP_TIMEOUT). Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        for p in self._procs:
            try:
                os.write(p.wake, b"q")
            except OSError:
                pass
            if not p.ready and p.popen.poll() is None:
                p.popen.terminate()  # still starting: it reads no pipe yet
            p.close_pipes()
        deadline = wallclock.monotonic() + STOP_TIMEOUT
        for p in self._procs:
            try:
                p.popen.wait(max(0.0, deadline - wallclock.monotonic()))
            except subprocess.TimeoutExpired:
                p.popen.kill()
                p.popen.wait()
        if self.worker is not None:
            self.worker.close()
            self.worker = None
        self.registry.release()
        if self.transport.path is not None and os.environ.get(PROFILES_FILE) == str(self.transport.path):
            if self._environ_before is None:
                os.environ.pop(PROFILES_FILE, None)
            else:
                os.environ[PROFILES_FILE] = self._environ_before
        self.transport.close()
        for fd in (self.notify_r, self.notify_w):
            try:
                os.close(fd)
            except OSError:
                pass

    def _spawn(self, index: int, check: bool) -> _Process:
        wake_r, wake_w = os.pipe()
        status_r, status_w = os.pipe()
        root = str(Path(__file__).resolve().parent.parent)
        env = dict(os.environ)
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        self.transport.apply(env)
        env.setdefault("RCUTILS_CONSOLE_OUTPUT_FORMAT", LOG_FORMAT)  # one log format with batchsim's own lines
        argv = [sys.executable, "-m", "ros_bridge.worker", str(index), str(wake_r), str(status_w), str(self.notify_w)]
        popen = subprocess.Popen(
            argv + (["--check"] if check else []),
            stdin=subprocess.PIPE,
            pass_fds=(wake_r, status_w, self.notify_w),
            env=env,
            start_new_session=True,  # Ctrl-C goes to the physics process, which stops the workers
        )
        os.close(wake_r)
        os.close(status_w)
        self._keep_off_avoided_cpus(popen.pid)
        try:
            popen.stdin.write(pickle.dumps(self.plan))
            popen.stdin.close()
        except BrokenPipeError:
            pass
        except BaseException:  # interrupted (Ctrl-C) while handing the plan over: no orphan
            popen.kill()
            popen.wait()
            for fd in (wake_w, status_r):
                os.close(fd)
            raise
        os.set_blocking(wake_w, False)
        os.set_blocking(status_r, False)
        return _Process(index, popen, wake_w, status_r)

    def _keep_off_avoided_cpus(self, pid: int) -> None:
        """The worker's cores: this process's, less the loop thread's (`avoid_cpus`), set
        before it starts a thread of its own (it is still importing)."""
        if self._cpus:  # never none: a loop pinned to every core leaves the workers where they are
            try:
                os.sched_setaffinity(pid, self._cpus)
            except OSError:  # gone already: supervise() says so
                pass

    def _await_ready(self, procs: list[_Process]) -> None:
        timeout = max((start_timeout(hi - lo) for lo, hi in (self.plan.ranges[p.index] for p in procs)), default=START_TIMEOUT)
        deadline = wallclock.monotonic() + timeout
        waiting = {p.status: p for p in procs}
        lines: dict[int, bytes] = {fd: b"" for fd in waiting}
        while waiting:
            left = deadline - wallclock.monotonic()
            if left <= 0:
                raise WorkerError(f"bridge worker {next(iter(waiting.values())).index} did not start in {timeout:g} s")
            ready, _, _ = select.select(list(waiting), [], [], min(left, 0.2))
            for fd in ready:
                chunk = os.read(fd, 4096)
                lines[fd] += chunk
                if b"\n" in lines[fd] or not chunk:
                    p = waiting.pop(fd)
                    self._started(p, lines[fd].decode(errors="replace").strip())
            for fd, p in list(waiting.items()):
                if p.popen.poll() is not None and fd not in ready:
                    waiting.pop(fd)
                    self._started(p, lines[fd].decode(errors="replace").strip())

    def _started(self, p: _Process, line: str) -> None:
        if line == "ready":
            p.ready = True
            return
        if line.startswith("conflict "):
            kind, _, message = line[len("conflict ") :].partition(" ")
            raise FleetConflict(kind, message)
        detail = line[len("error ") :] if line.startswith("error ") else f"exit code {p.popen.poll()}"
        raise WorkerError(f"bridge worker {p.index} failed to start: {detail}")

    def supervise(self) -> None:
        """At most every SUPERVISE s: stamp that the physics process runs (liveness.physics_alive),
        run `watchers` (the other helper processes' checks: the web view's, ViewProcess.watch),
        restart a worker that died (with a back-off) and say when one is back."""
        now = wallclock.monotonic()
        if now < self._next_supervise:
            return
        self._next_supervise = now + SUPERVISE
        liveness.physics_alive(self.memory, wallclock.time())  # the loop looked: the physics process runs
        for watch in self.watchers:
            watch()
        self.throttle.flush()  # windows that closed: how many lines each held back
        for j, p in enumerate(self._procs):
            if not p.ready and p.status >= 0:  # a restarted worker: is it up?
                try:
                    line = os.read(p.status, 4096)
                except BlockingIOError:
                    line = None
                if line is not None and line.startswith(b"ready"):
                    p.ready = True
                    lo, hi = self.plan.ranges[j]
                    self.throttle.warn(("worker", j, "back"), f"bridge worker {j} is back: {self._worlds(lo, hi)} are served again")
            code = p.popen.poll()
            if code is None:
                if p.ready:
                    self._watch(j, p, now)
                continue
            lo, hi = self.plan.ranges[j]
            if p.died_at == 0.0:
                hold = "go safe after the command timeout" if self.command_timeout else "hold their last commands"
                self.throttle.warn(
                    ("worker", j, "died"),
                    f"bridge worker {j} (pid {p.popen.pid}) died with exit code {code}: {self._worlds(lo, hi)} "
                    f"{hold}; restarting it",
                )
                p.died_at = now
            if now - p.died_at < min(30.0, 0.5 * 2 ** min(p.restarts, 6)) and p.restarts:
                continue  # it died again soon after a restart: back off
            replacement = self._spawn(j, check=False)
            replacement.restarts = p.restarts + 1
            p.close_pipes()
            self._procs[j] = replacement

    def _watch(self, j: int, p: _Process, now: float) -> None:
        """A live worker that stopped ticking: reported, then killed (and restarted as one that died)."""
        beat = liveness.beat(self.memory, j)
        if beat != p.beat:
            p.beat, p.beat_at = beat, now
            if p.hung_since:
                p.hung_since = 0.0
                liveness.mark_hung(self.memory, j, 0.0)
                self.throttle.warn(("worker", j, "answers"), f"bridge worker {j} answers again")
            return
        silent = now - p.beat_at
        lo, hi = self.plan.ranges[j]
        if silent >= HUNG_AFTER and not p.hung_since:
            p.hung_since = now
            liveness.mark_hung(self.memory, j, wallclock.time() - silent)
            self.throttle.warn(
                ("worker", j, "hung"),
                f"bridge worker {j} (pid {p.popen.pid}) has not answered for {silent:.1f} s (busy or hung): "
                f"{self._worlds(lo, hi)} are not served; restarting it unless it answers within {HUNG_RESTART - silent:.0f} s",
            )
        elif silent >= HUNG_RESTART:
            self.throttle.warn(("worker", j, "killed"), f"bridge worker {j} did not answer for {silent:.0f} s: killed")
            p.popen.kill()  # the next look restarts it, as one that died
            liveness.mark_hung(self.memory, j, 0.0)
            p.beat_at = now

    def _worlds(self, lo: int, hi: int) -> str:
        return worlds_label(self.plan.namespaces, lo, hi)

    def wake(self, worker: int) -> None:
        """Worker `worker`'s tick: a new snapshot or an answered request."""
        if self.worker is not None or worker >= len(self._procs):
            return
        try:
            os.write(self._procs[worker].wake, b"w")
        except (BlockingIOError, OSError):
            pass  # its pipe is full (it is behind) or it is gone (supervision restarts it)

    def wake_all(self) -> None:
        """Every worker's tick (the in-process one runs here)."""
        if self.worker is not None:
            self.worker.tick()
        else:
            for j in range(len(self._procs)):
                self.wake(j)
