"""A fleet over ROS 2 at scale: what the bridge costs the physics, and what reaches subscribers.

    .venv/bin/python benchmarks/fleet.py --preset gpu     # the GPU host's target set (warp, arm)
    .venv/bin/python benchmarks/fleet.py --preset 2core   # this project's 2-core CI machine
    .venv/bin/python benchmarks/fleet.py --backend cpu --worlds 16,64 --control-rate 100
    .venv/bin/python benchmarks/fleet.py --preset gpu --cpu-affinity 0   # the loop on core 0, the rest off it

Per size, each in fresh processes on a private ROS domain (discovery limited to this host):

  no ROS      `batchsim --no-ros --rtf 0`: physics steps/s, flat out
  flat out    `batchsim --rtf 0` with the bridge, while K subscriber processes take every
              world's joint_states: steps/s, its ratio to no ROS, and joint_states received
              against published (counted by the workers as they publish, read from their
              /diagnostics `published joint_states` by one more process; both counts
              interpolated at the window's edges between their samples, the subscribers'
              every 0.25 s and the workers' every 0.5 s, so where every message arrives the
              two can differ by about a publishing round's messages per edge either way; the loop never waits for the workers: a worker that
              falls behind publishes the newest state and skips the rest)
  real time   `batchsim --rtf 1`, the same subscribers: the RTF held (median and worst
              one-second window), joint_states received/s against published/s (the
              workers' count, as above) and against worlds x publish rate x RTF
  heard after seconds from batchsim's start line (its workers up) until every world's
              joint_states reached a subscriber, in the real-time run

Subscribers count raw (serialized) messages in processes of their own, each taking a
contiguous share of the worlds, so their deserialization does not weigh on the fleet.
The last line is `ratio <flat out with ROS / without, at the largest size>`. Nothing is
asserted: speed is measured here, never in tests.
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import signal
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
LOCALHOST = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
PUBLISHED_KEY = "published joint_states"  # per world in /diagnostics (ros_bridge/worker/diagnostics.py)
MISSED_KEY = "missed joint_states"  # ... due, not published: the worker read its snapshot too late

# per preset: backend, model, (worlds, control Hz, joint_states Hz) per size, subscriber
# processes, physics threads (2 cores: one for the physics, one for the bridge and subscriber)
PRESETS = {
    "gpu": dict(backend="warp", model="arm", sizes=[(1024, 100.0, 100.0), (4096, 100.0, 25.0)], subscribers=8, threads=None),
    "2core": dict(backend="cpu", model="arm", sizes=[(16, 1000.0, 1000.0), (64, 100.0, 100.0)], subscribers=1, threads=1),
}


# --- a subscriber process ---
def subscriber(domain: int, lo: int, hi: int, template: str) -> None:
    """Count joint_states of worlds lo..hi-1; print `heard <wall>` once all were heard and
    `count <wall> <total>` every 0.25 s, until stdin closes."""
    os.environ.update(LOCALHOST)
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import JointState

    context = Context()
    rclpy.init(context=context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    node = Node(f"fleet_benchmark_{lo}", context=context)
    counts = [0] * (hi - lo)

    def counter(k: int):
        def callback(msg: bytes) -> None:
            counts[k] += 1

        return callback

    for w in range(lo, hi):
        topic = "/" + template.format(i=w).strip("/") + "/joint_states"
        node.create_subscription(JointState, topic, counter(w - lo), 10, raw=True)
    executor, stop = executor_until_stdin_closes(context, node)
    heard = False
    next_report = time.time()
    while not stop.is_set():
        executor.spin_once(timeout_sec=0.05)
        now = time.time()
        if not heard and all(counts):
            heard = True
            print(f"heard {now:.3f}", flush=True)
        if now >= next_report:
            next_report = now + 0.25
            print(f"count {now:.3f} {sum(counts)}", flush=True)
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown(context=context)


def listen_to_diagnostics(domain: int, node_name: str, callback: Callable[[Any], None]) -> None:
    """In a child process: `callback(msg)` for every /diagnostics message (a DiagnosticArray:
    a worker publishes its own worlds' statuses, the first world's namespace naming it),
    until the parent closes this process's stdin."""
    os.environ.update(LOCALHOST)
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.context import Context
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions

    context = Context()
    rclpy.init(context=context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    node = Node(node_name, context=context)
    node.create_subscription(DiagnosticArray, "/diagnostics", callback, 100)
    executor, stop = executor_until_stdin_closes(context, node)
    while not stop.is_set():
        executor.spin_once(timeout_sec=0.05)
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown(context=context)


def published_listener(domain: int) -> None:
    """Print `published <wall> <worker> <total> <missed>` for every /diagnostics message: the sum
    of its worlds' `published joint_states` and `missed joint_states`, until stdin closes."""

    def callback(msg: Any) -> None:
        now = time.time()
        worker, total, missed = None, 0, 0
        for status in msg.status:
            for kv in status.values:
                if kv.key == PUBLISHED_KEY:
                    worker = worker or status.hardware_id
                    total += int(kv.value)
                elif kv.key == MISSED_KEY:
                    missed += int(kv.value)
        if worker is not None:
            print(f"published {now:.3f} {worker} {total} {missed}", flush=True)

    listen_to_diagnostics(domain, "fleet_benchmark_published", callback)


def executor_until_stdin_closes(context, node):
    """A child process's EventsExecutor for `node`, and an event set once the parent closes
    the child's stdin (how these benchmarks stop their helper processes)."""
    from rclpy.experimental import EventsExecutor

    executor = EventsExecutor(context=context)
    executor.add_node(node)
    stop = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    return executor, stop


# --- the parent ---
def at(samples: list[tuple[float, float]], t: float) -> float | None:
    """A count sampled at wall times (ascending), linearly interpolated at `t`; None where
    `t` is not inside the samples."""
    for (ta, ca), (tb, cb) in zip(samples, samples[1:], strict=False):
        if ta <= t <= tb:
            return ca if tb == ta else ca + (cb - ca) * (t - ta) / (tb - ta)
    return None


def wait_sampled(series: list[list[tuple[float, float]]], t: float, timeout: float) -> None:
    """Until every series has a sample after `t` (a count can then be interpolated at `t`)."""
    deadline = time.time() + timeout
    while any(not s or s[-1][0] < t for s in series) and time.time() < deadline:
        time.sleep(0.05)


class Published:
    """A process reading the workers' /diagnostics: joint_states published, per worker."""

    def __init__(self, domain: int, reserved: tuple[int, ...] = ()):
        env = {**os.environ, **LOCALHOST, "PYTHONPATH": _pythonpath()}
        self.proc = subprocess.Popen(
            [sys.executable, __file__, "--published", str(domain)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env
        )
        keep_off(self.proc, reserved)
        self.samples: dict[str, list[tuple[float, float]]] = {}
        self.missed: dict[str, list[tuple[float, float]]] = {}  # per worker, as samples
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            parts = line.split()
            if len(parts) == 5 and parts[0] == "published":
                self.samples.setdefault(parts[2], []).append((float(parts[1]), float(parts[3])))
                self.missed.setdefault(parts[2], []).append((float(parts[1]), float(parts[4])))

    def total(self, t: float, missed: bool = False) -> float:
        """joint_states all workers had published (`missed`: were due and did not publish) by
        wall time `t` (interpolated); NaN where a worker's /diagnostics do not reach that far
        (or none came): which, on stderr."""
        series = dict(self.missed if missed else self.samples)
        counts = {worker: at(s, t) for worker, s in series.items()}
        late = sorted(worker for worker, c in counts.items() if c is None)
        if not counts or late:
            spans = ", ".join(f"{w} {series[w][0][0] - t:+.1f}..{series[w][-1][0] - t:+.1f} s" for w in late[:4])
            print(f"# published: no /diagnostics at the window's edge from {len(late)} of {len(counts)} workers ({spans})",
                  file=sys.stderr, flush=True)  # fmt: skip
            return float("nan")
        return float(sum(counts.values()))

    def wait_ready(self, timeout: float, settle: float = 1.5) -> None:
        """Until some worker's /diagnostics came and no new worker's for `settle` seconds: a
        window opened before a worker's first /diagnostics cannot count it at its start (a
        worker of 512 worlds publishes its first ones seconds after the fleet runs)."""
        deadline = time.time() + timeout
        seen, since = 0, time.time()
        while time.time() < deadline:
            n = len(self.samples)
            if n != seen:
                seen, since = n, time.time()
            elif n and time.time() - since >= settle:
                return
            time.sleep(0.1)

    def close(self) -> None:
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def keep_off(proc: subprocess.Popen, reserved: tuple[int, ...]) -> None:
    """Keep a helper process off the loop's cores (`--cpu-affinity`) and their other hardware
    threads, as batchsim keeps its workers, and as a user's taskset would."""
    from batchsim.loop.realtime import with_siblings

    if reserved:
        os.sched_setaffinity(proc.pid, set(os.sched_getaffinity(0)) - with_siblings(reserved))


def _pythonpath() -> str:
    """The project first, then whatever the caller's PYTHONPATH holds (on the GPU host, the
    MuJoCo wheels' directory)."""
    extra = os.environ.get("PYTHONPATH")
    return str(ROOT) + (os.pathsep + extra if extra else "")


def children(pid: int) -> list[int]:
    """The direct child processes of `pid` (Linux /proc); none where it cannot say."""
    out = []
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/children") as f:
                out += [int(c) for c in f.read().split()]
    except OSError:
        pass
    return out


def worker_pid(pid: int) -> int | None:
    """Bridge worker 0's process of batchsim process `pid`, or None."""
    for child in children(pid):
        try:
            with open(f"/proc/{child}/cmdline", "rb") as f:
                argv = f.read().split(b"\0")
        except OSError:
            continue
        if b"ros_bridge.worker" in argv and argv[argv.index(b"ros_bridge.worker") + 1] == b"0":
            return child
    return None


def rss_mb(pid: int) -> float:
    """Process `pid`'s resident memory (VmRSS) in MB; NaN where /proc cannot say."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def client_node(domain: int, name: str) -> tuple[Any, Any, Any]:
    """(context, node, executor) of a client node of this process on `domain`, localhost only:
    a benchmark's probe of a fleet (`rclpy.try_shutdown(context=context)` ends it)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    os.environ.update(LOCALHOST)
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    node = Node(name, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    return context, node, executor


class Subscribers:
    """K subscriber processes sharing the worlds."""

    def __init__(self, domain: int, worlds: int, k: int, template: str, reserved: tuple[int, ...] = ()):
        k = max(1, min(k, worlds))
        edges = [round(i * worlds / k) for i in range(k + 1)]
        env = {**os.environ, **LOCALHOST, "PYTHONPATH": _pythonpath()}
        self.procs = [
            subprocess.Popen(
                [sys.executable, __file__, "--subscriber", str(domain), str(a), str(b), template],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env,
            )  # fmt: skip
            for a, b in zip(edges[:-1], edges[1:], strict=True)
        ]
        for proc in self.procs:
            keep_off(proc, reserved)
        self.heard: list[float | None] = [None] * len(self.procs)
        self.samples: list[list[tuple[float, int]]] = [[] for _ in self.procs]
        self._threads = [threading.Thread(target=self._read, args=(i,), daemon=True) for i in range(len(self.procs))]
        for t in self._threads:
            t.start()

    def _read(self, i: int) -> None:
        for line in self.procs[i].stdout:
            parts = line.split()
            if parts and parts[0] == "heard":
                self.heard[i] = float(parts[1])
            elif parts and parts[0] == "count":
                self.samples[i].append((float(parts[1]), int(parts[2])))

    def all_heard(self) -> float | None:
        return None if any(h is None for h in self.heard) else max(self.heard)

    def total(self, t: float) -> float:
        """Messages received by all subscribers up to wall time `t` (interpolated between their
        reports; before a subscriber's first report, 0; after its last, its last)."""
        out = 0.0
        for s in self.samples:
            s = list(s)
            c = at(s, t)
            if c is None:
                c = s[-1][1] if s and t > s[-1][0] else 0.0
            out += c
        return out

    def close(self) -> None:
        for p in self.procs:
            try:
                p.stdin.close()
            except OSError:
                pass
        for p in self.procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()


class Batchsim:
    """A `batchsim` process; its stderr lines with their wall times."""

    def __init__(self, args: list[str], domain: int | None):
        env = {**os.environ, **LOCALHOST, "PYTHONUNBUFFERED": "1", "PYTHONPATH": _pythonpath()}
        if domain is not None:
            env["ROS_DOMAIN_ID"] = str(domain)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "batchsim.cli", "--status-every", "1", *args], stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, env=env
        )
        self.lines: list[tuple[float, str]] = []
        self.started: float | None = None
        self.substeps = 1  # physics steps per control period, from the start line
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            now = time.time()
            self.lines.append((now, line.rstrip()))
            if self.started is None and line.startswith("batchsim: ") and " x " in line:
                m = re.search(r"\((\d+) x [0-9.e+-]+ s\)", line)
                self.substeps = int(m.group(1)) if m else 1
                self.started = now

    def status(self, since: float, until: float) -> list[tuple[float, float]]:
        """(rtf, steps/s) of the status lines printed between two wall times."""
        out = []
        for t, line in self.lines:
            m = re.search(r"\| rtf\s+([0-9.]+) \| ([0-9.]+)([kM]) steps/s", line)
            if m and since <= t <= until:
                out.append((float(m.group(1)), float(m.group(2)) * (1e6 if m.group(3) == "M" else 1e3)))
        return out

    def sim_rate(self, since: float, until: float) -> float:
        """Sim seconds per wall second between two wall times, from the status lines' sim time
        (printed each second, to 0.01 s) interpolated at both; NaN without lines around both.
        Waits up to 2.5 s for a line after `until`."""
        deadline = time.time() + 2.5
        while time.time() < deadline and not any(t > until and " rtf " in line for t, line in list(self.lines)):
            time.sleep(0.05)
        samples = []
        for t, line in list(self.lines):
            m = re.search(r"sim\s+([0-9.]+) s \|", line)
            if m:
                samples.append((t, float(m.group(1))))
        a, b = at(samples, since), at(samples, until)
        return float("nan") if a is None or b is None else (b - a) / (until - since)

    def stalls(self, since: float, until: float) -> int:
        """Warnings of a bridge worker without a tick for a second (ros_bridge/supervisor.py)
        between two wall times: in such a second its worlds publish nothing."""
        return sum(1 for t, line in self.lines if since <= t <= until and "has not answered" in line)

    def wait_started(self, timeout: float) -> None:
        deadline = time.time() + timeout
        while self.started is None:
            if self.proc.poll() is not None or time.time() > deadline:
                raise RuntimeError("batchsim did not start:\n" + "\n".join(line for _, line in self.lines[-20:]))
            time.sleep(0.05)

    def wait_running(self, timeout: float) -> None:
        """Until the first status line: a GPU backend compiles its kernels on the first step,
        after the start line, and a window opened before that would time the compiler."""
        self.wait_started(timeout)
        deadline = time.time() + timeout
        while not self.status(0.0, float("inf")):
            if self.proc.poll() is not None or time.time() > deadline:
                raise RuntimeError("batchsim printed no status line:\n" + "\n".join(line for _, line in self.lines[-20:]))
            time.sleep(0.05)

    def stop(self) -> str:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        self._thread.join(timeout=5)
        return "\n".join(line for _, line in self.lines[-5:])


def run_size(opts: argparse.Namespace, worlds: int, control: float, publish: float, domain: int) -> dict:
    common = ["--worlds", str(worlds), "--model", opts.model, "--backend", opts.backend, "--controllers", "none"]
    common += ["--control-rate", f"{control:g}"]
    if opts.threads:
        common += ["--threads", str(opts.threads)]
    if opts.devices:
        common += ["--devices", opts.devices]
    reserved = tuple(int(c) for c in opts.cpu_affinity.split(",")) if opts.cpu_affinity else ()
    if reserved:  # the loop's thread on these cores, with ROS and without; the workers keep off them
        common += ["--cpu-affinity", opts.cpu_affinity]
    ros = common + ["--publish-rate", f"{publish:g}"]
    if opts.bridge_workers is not None:
        ros += ["--bridge-workers", str(opts.bridge_workers)]
    out: dict = {"worlds": worlds, "control": control, "publish": publish}

    def window(b: Batchsim) -> list[tuple[float, float]]:
        b.wait_running(opts.start_timeout)
        time.sleep(opts.warmup)
        t0 = time.time()
        time.sleep(opts.seconds)
        return b.status(t0, time.time() + 0.5)

    b = Batchsim(common + ["--no-ros", "--rtf", "0"], None)
    try:
        rows = window(b)
    finally:
        b.stop()
    out["no_ros"] = statistics.median(s for _, s in rows) if rows else float("nan")

    subs = Subscribers(domain, worlds, opts.subscriber_processes, "world_{i}", reserved)
    published = Published(domain, reserved)
    try:
        b = Batchsim(ros + ["--rtf", "0"], domain)
        try:
            b.wait_running(opts.start_timeout)
            time.sleep(opts.warmup)
            published.wait_ready(30.0)
            t0 = time.time()
            time.sleep(opts.seconds)
            t1 = time.time()
            # both counts interpolated at t0 and t1: every subscriber (every 0.25 s) and every
            # worker's /diagnostics (every 0.5 s) reported past t1
            wait_sampled([*subs.samples, *published.samples.values()], t1, 5.0)
            rows = b.status(t0, t1 + 0.8)
        finally:
            b.stop()
        out["flat_out"] = statistics.median(s for _, s in rows) if rows else float("nan")
        out["flat_out_received"] = (subs.total(t1) - subs.total(t0)) / (t1 - t0)
        out["flat_out_published"] = (published.total(t1) - published.total(t0)) / (t1 - t0)
    finally:
        published.close()
        subs.close()

    subs = Subscribers(domain, worlds, opts.subscriber_processes, "world_{i}", reserved)
    published = Published(domain, reserved)
    try:
        time.sleep(1.0)  # the subscribers' own start
        b = Batchsim(ros + ["--rtf", "1"], domain)
        try:
            b.wait_started(opts.start_timeout)
            deadline = time.time() + opts.heard_timeout
            while subs.all_heard() is None and time.time() < deadline and b.proc.poll() is None:
                time.sleep(0.05)
            heard = subs.all_heard()
            out["heard"] = (heard - b.started) if heard is not None else float("nan")
            time.sleep(opts.warmup)
            published.wait_ready(30.0)
            t0 = time.time()
            time.sleep(opts.seconds)
            t1 = time.time() - 0.3  # the subscribers' last reports lag a little
            # both edges counted once every report past them came: at t0 itself the newest
            # report was up to 0.25 s old, and the window counted those messages as its own
            wait_sampled([*subs.samples, *published.samples.values()], t1, 5.0)
            c0, c1 = subs.total(t0), subs.total(t1)
            out["published"] = (published.total(t1) - published.total(t0)) / (t1 - t0)
            out["missed"] = (published.total(t1, missed=True) - published.total(t0, missed=True)) / (t1 - t0)
            out["sim_rate"] = b.sim_rate(t0, t1)
            out["stalls"] = b.stalls(t0, t1)
            rows = b.status(t0, t1 + 0.8)
        finally:
            b.stop()
    finally:
        published.close()
        subs.close()
    rtfs = [r for r, _ in rows]
    out["rtf"] = statistics.median(rtfs) if rtfs else float("nan")
    out["rtf_min"] = min(rtfs) if rtfs else float("nan")
    out["received"] = (c1 - c0) / (t1 - t0)
    # sim seconds per wall second over the window, from the status lines' sim time (the RTF they
    # print is rounded to 0.01, worth 1 % of the expected count); the median RTF where not
    out["expected"] = worlds * publish * (out["sim_rate"] if out["sim_rate"] == out["sim_rate"] else out["rtf"])
    return out


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--subscriber":
        domain, lo, hi = (int(a) for a in sys.argv[2:5])
        subscriber(domain, lo, hi, sys.argv[5])
        return
    if len(sys.argv) > 1 and sys.argv[1] == "--published":
        published_listener(int(sys.argv[2]))
        return
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", choices=sorted(PRESETS), default=None, help="a target set (overrides the size flags)")
    p.add_argument("--backend", default="cpu")
    p.add_argument("--model", default="arm")
    p.add_argument("--worlds", default="16,64", help="comma-separated world counts")
    p.add_argument("--control-rate", type=float, default=100.0)
    p.add_argument("--publish-rate", type=float, default=None, help="joint_states Hz (default: the control rate)")
    p.add_argument("--subscriber-processes", type=int, default=max(1, min(8, (os.cpu_count() or 2) // 2)))
    p.add_argument("--bridge-workers", type=int, default=None, help="default: batchsim's own choice")
    p.add_argument("--devices", default=None, help="GPU backends: the devices the worlds are split over ('all', '0,1')")
    p.add_argument("--threads", type=int, default=None, help="cpu backend: physics threads")
    p.add_argument(
        "--cpu-affinity", default="", metavar="I,J", help="batchsim's --cpu-affinity (both runs); the subscribers keep off these cores"
    )
    p.add_argument("--seconds", type=float, default=8.0, help="measurement window, wall seconds")
    p.add_argument("--warmup", type=float, default=2.0)
    p.add_argument("--start-timeout", type=float, default=300.0, help="seconds batchsim may take to start (GPU compiles)")
    p.add_argument("--heard-timeout", type=float, default=120.0)
    p.add_argument("--domain", type=int, default=71)
    opts = p.parse_args()
    if opts.preset:
        preset = PRESETS[opts.preset]
        opts.backend, opts.model = preset["backend"], preset["model"]
        sizes = preset["sizes"]
        if "--subscriber-processes" not in sys.argv:
            opts.subscriber_processes = preset["subscribers"]
        if opts.threads is None:
            opts.threads = preset["threads"]
        if "--heard-timeout" not in sys.argv:
            opts.heard_timeout = 60.0  # 3 times the target: a slower discovery still leaves time for the rest
    else:
        sizes = [(int(w), opts.control_rate, opts.publish_rate or opts.control_rate) for w in opts.worlds.split(",")]
    versions = _versions()
    print(
        f"# {platform.node() or 'host'}, {os.cpu_count()} cores, Python {platform.python_version()}, {versions}, "
        f"{opts.backend} {opts.model}, physics threads {opts.threads or 'default'}, "
        f"{opts.subscriber_processes} subscriber processes, bridge workers {opts.bridge_workers if opts.bridge_workers is not None else 'default'}, "
        f"loop on cores {opts.cpu_affinity or 'any'}, "
        f"load {os.getloadavg()[0]:.1f}, {time.strftime('%Y-%m-%d')}"
    )  # fmt: skip
    print(
        "| worlds | control Hz | joint_states Hz | steps/s no ROS | steps/s flat out with ROS | ratio "
        "| joint_states/s flat out, received / published | RTF held (median / worst) "
        "| joint_states received/s | published/s | expected/s | all worlds heard after s |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |", flush=True)
    last = None
    began = time.monotonic()
    for worlds, control, publish in sizes:
        r = run_size(opts, worlds, control, publish, opts.domain)
        print(f"# {worlds} worlds measured in {time.monotonic() - began:.0f} s since the start; "
              f"{r['stalls']} worker stalls of 1 s or more in the real-time window; the workers missed "
              f"{r['missed']:,.0f} joint_states/s (due, their snapshots gone before read); sim {r['sim_rate']:.4f} s per s",
              file=sys.stderr, flush=True)  # fmt: skip
        last = r
        print(
            f"| {worlds} | {control:g} | {publish:g} | {r['no_ros']:,.0f} | {r['flat_out']:,.0f} | {r['flat_out'] / r['no_ros']:.3f} | "
            f"{r['flat_out_received']:,.0f} / {r['flat_out_published']:,.0f} | {r['rtf']:.2f} / {r['rtf_min']:.2f} | {r['received']:,.0f} | {r['published']:,.0f} | {r['expected']:,.0f} | {r['heard']:.1f} |",
            flush=True,
        )
    if last is not None:
        print(f"ratio {last['flat_out'] / last['no_ros']:.3f}")


def _versions() -> str:
    """The libraries' versions, from their distributions: rclpy has no `__version__` (the
    header said `rclpy ?`), and importing warp only to ask would start it."""
    from importlib import metadata

    parts = []
    for name, dist in (
        ("mujoco", "mujoco"),
        ("rclpy", "ros-jazzy-rclpy"),
        ("numpy", "numpy"),
        ("warp", "warp-lang"),
        ("mujoco_warp", "mujoco-warp"),
    ):
        try:
            parts.append(f"{name} {metadata.version(dist)}")
        except metadata.PackageNotFoundError:
            continue
    return ", ".join(parts)


if __name__ == "__main__":
    main()


def keep_in_flight(context: Any, executor: Any, send: Callable[[int], Any], outcome: Callable[[Any], str],
                   keys: tuple[str, str], outstanding: int, seconds: float) -> None:  # fmt: skip
    """A flooding client's run (service_flood.py, goal_flood.py): `outstanding` requests in flight
    for `seconds`, a new one sent as each is answered; `send(k)` sends the k-th and returns its
    future, `outcome(future)` names what came of it (one of `keys`). Spins until 2 s after the
    end, shuts `context` down and prints the two counts, as start_flooder's caller reads them."""
    stop = time.monotonic() + seconds
    counts = dict.fromkeys(keys, 0)
    sent = 0

    def next_one() -> None:
        nonlocal sent
        sent += 1
        send(sent - 1).add_done_callback(answered)

    def answered(future: Any) -> None:
        counts[outcome(future)] += 1
        if time.monotonic() < stop:
            next_one()

    for _ in range(outstanding):
        next_one()
    while time.monotonic() < stop + 2.0:
        executor.spin_once(timeout_sec=0.05)
    context.try_shutdown()
    print(" ".join(str(counts[k]) for k in keys), flush=True)


def start_flooder(script: str, world: int, domain: int, seconds: float, clients: int) -> subprocess.Popen:
    """`script --world W --flood DOMAIN SECONDS CLIENTS` in a process of its own (its flood()),
    its one line of counts on stdout."""
    env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(domain), "PYTHONPATH": _pythonpath()}
    return subprocess.Popen([sys.executable, script, "--world", str(world), "--flood", str(domain), str(seconds), str(clients)],
                            stdout=subprocess.PIPE, text=True, env=env)  # fmt: skip


def flood_args(doc: str, domain: int, what: str, flood: Callable[[int, int, float, int], None]) -> Any:
    """The flood benchmarks' flags (`what`: what is in flight); None where this process is the
    flooder that start_flooder started, after its `flood(domain, world, seconds, clients)` ran."""
    import argparse

    p = argparse.ArgumentParser(description=doc.splitlines()[0])
    p.add_argument("--seconds", type=float, default=10.0, help="each window")
    p.add_argument("--clients", type=int, default=32, help=f"the flood's {what} in flight")
    p.add_argument("--world", type=int, default=3, help="the flooded world")
    p.add_argument("--domain", type=int, default=domain)
    p.add_argument("--flood", nargs=3, type=float, help=argparse.SUPPRESS)  # the flooding process
    opts = p.parse_args()
    if opts.flood:
        flood(int(opts.flood[0]), opts.world, opts.flood[1], int(opts.flood[2]))
        return None
    return opts
