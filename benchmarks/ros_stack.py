"""The ROS stack at fleet scale: joint_states and tf on every world, and action goals, at real time.

    .venv/bin/python benchmarks/ros_stack.py --preset 2core   # 16 arms, 100 Hz, a goal per world per second
    .venv/bin/python benchmarks/ros_stack.py --preset gpu     # 1024 arms on warp, 100 Hz, 1024 goals at once

The loop runs in this process (a SimLoop with the arm's default controllers and the ROS 2
bridge, its workers in processes of their own), paced at RTF 1. Beside it:

  subscribers   K processes, each taking a contiguous share of the worlds: every world's
                `joint_states` and `tf` (`/<ns>/tf`), counted raw (no deserialization);
                the first also takes the fleet-wide `/tf` (one message per bridge worker
                and period, every world's transforms in it)
  goal clients  G processes, each with a FollowJointTrajectory client per world of its
                share: `burst` sends every world one goal at the same moment and waits for
                every result; `rate` sends every world a goal each 1/R s

Reported: the RTF held; the loop's own time per control period (read, controllers, bridge,
write, step; the pacing sleep excluded), median and worst, against the period's budget;
messages received against expected for each topic kind; goals sent, results by status,
and the time from a burst to its last result. With `--capacity`, the same host's plain
rclpy capacity for small messages, K publisher and K subscriber processes, measured in the
same run, to show where Python subscribers are the ceiling. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import gc
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from fleet import _versions  # benchmarks/fleet.py: the libraries' versions for the header

ROOT = Path(__file__).resolve().parent.parent
LOCALHOST = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
ARM = [f"joint{i}" for i in range(1, 7)]
JTC = "joint_trajectory_controller"

PRESETS = {
    "2core": dict(backend="cpu", worlds=16, control=100.0, subscribers=1, goal_clients=1, goals="rate", goal_rate=1.0),
    "gpu": dict(backend="warp", worlds=1024, control=100.0, subscribers=8, goal_clients=8, goals="burst", goal_rate=0.0),
}


def _env() -> dict[str, str]:
    extra = os.environ.get("PYTHONPATH")
    return {**os.environ, **LOCALHOST, "PYTHONPATH": str(ROOT) + (os.pathsep + extra if extra else "")}


def _init(domain: int, name: str):
    os.environ.update(LOCALHOST)
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions

    context = Context()
    rclpy.init(context=context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    return context, Node(name, context=context)


def _until_stdin_closes(go: list[float] | None = None) -> threading.Event:
    """An event set when the parent closes stdin; a `go <wall time>` line on it sets go[0]."""
    stop = threading.Event()

    def watch() -> None:
        for line in sys.stdin:
            if line.startswith("go ") and go is not None:
                go[0] = float(line.split()[1])
        stop.set()

    threading.Thread(target=watch, daemon=True).start()
    return stop


# --- child processes ---
def subscriber(domain: int, lo: int, hi: int, fleet_tf: bool) -> None:
    """Count joint_states and tf of worlds lo..hi-1 (and /tf), and the worlds heard on each:
    `count <wall> <js> <tf> <fleet tf> <worlds heard on js> <on tf>`."""
    from rclpy.experimental import EventsExecutor
    from sensor_msgs.msg import JointState
    from tf2_msgs.msg import TFMessage

    context, node = _init(domain, f"stack_subscriber_{lo}")
    counts = [0, 0, 0, 0, 0]  # messages on joint_states, tf, /tf; worlds heard on joint_states, tf
    heard = [bytearray(hi - lo), bytearray(hi - lo)]

    def counter(k: int, w: int = -1):
        def callback(msg: bytes) -> None:
            counts[k] += 1
            if w >= 0 and not heard[k][w]:
                heard[k][w] = 1
                counts[3 + k] += 1

        return callback

    for w in range(lo, hi):
        node.create_subscription(JointState, f"/world_{w}/joint_states", counter(0, w - lo), 10, raw=True)
        node.create_subscription(TFMessage, f"/world_{w}/tf", counter(1, w - lo), 100, raw=True)
    if fleet_tf:
        node.create_subscription(TFMessage, "/tf", counter(2), 100, raw=True)
    executor = EventsExecutor(context=context)
    executor.add_node(node)
    stop = _until_stdin_closes()
    next_report = time.time()
    while not stop.is_set():
        executor.spin_once(timeout_sec=0.05)
        if time.time() >= next_report:
            next_report = time.time() + 0.25
            print(f"count {time.time():.3f} {' '.join(map(str, counts))}", flush=True)


def goal_client(domain: int, lo: int, hi: int, mode: str, rate: float, start: float) -> None:
    """FollowJointTrajectory goals to worlds lo..hi-1: `ready <wall> <servers found>` once every
    action server is discovered, then, from the wall time of the parent's `go` line (or `start`
    if it is > 0), `sent <wall> <n>` and `result <wall> <status> <error_code>` per result."""
    from builtin_interfaces.msg import Duration
    from control_msgs.action import FollowJointTrajectory
    from rclpy.action import ActionClient
    from rclpy.executors import SingleThreadedExecutor
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    context, node = _init(domain, f"stack_goals_{lo}")
    clients = [ActionClient(node, FollowJointTrajectory, f"/world_{w}/{JTC}/follow_joint_trajectory") for w in range(lo, hi)]
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    threading.Thread(target=executor.spin, daemon=True).start()
    go = [start if start > 0 else float("inf")]
    stop = _until_stdin_closes(go)
    found = sum(bool(c.wait_for_server(timeout_sec=120)) for c in clients)
    print(f"ready {time.time():.3f} {found}", flush=True)
    lock = threading.Lock()

    def done(future) -> None:
        r = future.result()
        with lock:
            print(f"result {time.time():.3f} {r.status} {r.result.error_code} {r.result.error_string!r}", flush=True)

    def accepted(future) -> None:
        handle = future.result()
        if not handle.accepted:
            with lock:
                print(f"result {time.time():.3f} rejected -", flush=True)
            return
        handle.get_result_async().add_done_callback(done)

    def send(k: int) -> None:
        target = [0.3 * np.sin(k + j) for j in range(6)]
        point = JointTrajectoryPoint(positions=[float(x) for x in target], time_from_start=Duration(nanosec=500_000_000))
        goal = FollowJointTrajectory.Goal(trajectory=JointTrajectory(joint_names=ARM, points=[point]))
        for c in clients:
            c.send_goal_async(goal).add_done_callback(accepted)

    while time.time() < go[0] and not stop.is_set():
        time.sleep(0.002)
    k = 0
    while not stop.is_set():
        send(k)
        with lock:
            print(f"sent {time.time():.3f} {len(clients)}", flush=True)
        k += 1
        if mode == "burst":
            break
        stop.wait(1.0 / rate)
    stop.wait()
    time.sleep(2.0)  # the results of goals still in flight


def publisher_pair(domain: int, index: int, seconds: float) -> None:
    """Plain rclpy capacity: publish std_msgs/Float64MultiArray (6 values) flat out; `published <n>`."""
    from std_msgs.msg import Float64MultiArray

    context, node = _init(domain, f"cap_pub_{index}")
    pub = node.create_publisher(Float64MultiArray, f"/cap_{index}", 10)
    time.sleep(2.0)  # discovery
    msg = Float64MultiArray(data=[0.0] * 6)
    n, end = 0, time.time() + seconds
    while time.time() < end:
        pub.publish(msg)
        n += 1
    print(f"published {n}", flush=True)


def capacity_subscriber(domain: int, index: int, seconds: float) -> None:
    from rclpy.experimental import EventsExecutor
    from std_msgs.msg import Float64MultiArray

    context, node = _init(domain, f"cap_sub_{index}")
    count = [0]
    node.create_subscription(Float64MultiArray, f"/cap_{index}", lambda m: count.__setitem__(0, count[0] + 1), 10, raw=True)
    executor = EventsExecutor(context=context)
    executor.add_node(node)
    end = time.time() + seconds + 3.0
    while time.time() < end:
        executor.spin_once(timeout_sec=0.05)
    print(f"received {count[0]}", flush=True)


# --- the parent ---
class Children:
    """Child processes of this script and their output lines (`lines[i]`: each line's words).

    Their output goes to files, read when asked: no reader thread in the loop's process,
    where it would hold the GIL the loop needs (the command's process has none either)."""

    def __init__(self, argvs: list[list[str]], avoid_cpus: frozenset[int] = frozenset()):
        self._files = [tempfile.TemporaryFile("w+") for _ in argvs]
        self.procs = [
            subprocess.Popen([sys.executable, __file__, *a], stdin=subprocess.PIPE, stdout=f, text=True, env=_env())
            for a, f in zip(argvs, self._files, strict=True)
        ]
        for p in self.procs if avoid_cpus else ():  # as a user's `taskset -c` keeps their nodes off the loop's core
            os.sched_setaffinity(p.pid, os.sched_getaffinity(0) - avoid_cpus)

    @property
    def lines(self) -> list[list[list[str]]]:
        out = []
        for f in self._files:
            f.seek(0)
            text = f.read()
            whole = text[: text.rfind("\n") + 1]  # a line being written is not read yet
            out.append([line.split() for line in whole.splitlines()])
        return out

    def tell(self, line: str) -> None:
        for p in self.procs:
            p.stdin.write(line + "\n")
            p.stdin.flush()

    def close(self, timeout: float = 10.0) -> None:
        for p in self.procs:
            try:
                p.stdin.close()
            except OSError:
                pass
        for p in self.procs:
            try:
                p.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                p.kill()


def _shares(n: int, k: int) -> list[tuple[int, int]]:
    k = max(1, min(k, n))
    edges = [round(i * n / k) for i in range(k + 1)]
    return list(zip(edges[:-1], edges[1:], strict=True))


def _counted(children: Children, at: float) -> np.ndarray:
    """joint_states, per-world tf and fleet tf received by all subscribers up to wall time `at`."""
    total = np.zeros(3)
    for lines in children.lines:
        before = [line for line in list(lines) if line[0] == "count" and float(line[1]) <= at]
        if before:
            total += [float(x) for x in before[-1][2:5]]
    return total


def _heard(children: Children) -> tuple[int, int]:
    """Worlds heard so far on joint_states and on their tf, over all subscribers."""
    last = [[line for line in lines if line[0] == "count"][-1:] for lines in children.lines]
    return (sum(int(c[0][5]) for c in last if c), sum(int(c[0][6]) for c in last if c))


def _all_heard(children: Children, shares: list[tuple[int, int]]) -> float | None:
    """The wall time by which every world was heard on joint_states and on tf (None: not yet)."""
    when = []
    for lines, (lo, hi) in zip(children.lines, shares, strict=True):
        done = [float(line[1]) for line in lines if line[0] == "count" and int(line[5]) == int(line[6]) == hi - lo]
        if not done:
            return None
        when.append(done[0])
    return max(when)


def run(opts: argparse.Namespace) -> None:
    os.environ.update(LOCALHOST)
    os.environ["ROS_DOMAIN_ID"] = str(opts.domain)
    import batchsim
    from batchsim.backends import backend_class
    from batchsim.controllers import default_controllers, load_controllers
    from batchsim.loop import SimLoop
    from ros_bridge.bridge import BridgeOptions, start_bridge

    options = {"nthread": opts.threads} if opts.threads else {}
    if opts.devices:  # one process per device, as `batchsim --devices` runs them
        have = backend_class(batchsim.Backend.parse(opts.backend)).available_devices()
        options.update(devices=have if opts.devices == "all" else [have[int(d)] for d in opts.devices.split(",")], processes=True)
    sim = batchsim.make(opts.model, opts.worlds, opts.backend, **options)
    sim.configure()
    sim.activate()
    manager = load_controllers(default_controllers(opts.model), sim.spec, opts.worlds)
    loop = SimLoop(
        sim,
        control_rate=opts.control_rate,
        rtf=1.0,
        participants=[manager],
        thread_priority=opts.thread_priority,
        cpu_affinity=opts.cpu_affinity,
    )
    reserved = frozenset(opts.cpu_affinity) if opts.reserve_loop_cores else frozenset()
    host = start_bridge(sim, loop, BridgeOptions(workers=opts.bridge_workers), manager)
    nworker = host.plan.nworker
    for pid in host.worker_pids if opts.worker_nice else ():  # the workers yield the cores to the loop
        os.setpriority(os.PRIO_PROCESS, pid, opts.worker_nice)
    periods: list[tuple[float, float]] = []  # (wall time at the start, the period's own seconds)
    phases: list[dict[str, float]] = []  # per period: seconds in each part (read, step, each participant's hooks)
    current: dict[str, float] = {}
    run_period = loop.run_period

    def clocked(name: str, fn):
        def call(*args, **kwargs):
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                current[name] = current.get(name, 0.0) + time.perf_counter() - t

        return call

    for name in ("read", "write", "step"):
        setattr(sim, name, clocked(name, getattr(sim, name)))
    for part in loop.participants:
        for hook in ("update", "after_write"):  # `step` holds the while_stepping hooks (the bridge's snapshot on a GPU)
            if hasattr(part, hook):
                setattr(part, hook, clocked(f"{type(part).__name__}.{hook}", getattr(part, hook)))
    collections: list[tuple[int, float, float]] = []  # (generation, wall time at its start, seconds)
    gc_started = [0.0]

    def on_gc(phase: str, info: dict) -> None:
        if phase == "start":
            gc_started[0] = time.perf_counter()
        else:
            collections.append((info["generation"], time.time(), time.perf_counter() - gc_started[0]))

    gc.callbacks.append(on_gc)
    if opts.gc_freeze:
        gc.freeze()  # what start-up made is never scanned again: no long collections in the loop

    def timed(nstep: int | None = None) -> None:
        current.clear()
        t = time.perf_counter()
        run_period(nstep)
        periods.append((time.time(), time.perf_counter() - t))
        phases.append(dict(current))

    loop.run_period = timed
    stop = threading.Event()
    runner = threading.Thread(target=lambda: loop.run(), daemon=True)
    runner.start()
    subs = Children(
        [["--subscriber", str(opts.domain), str(lo), str(hi), str(int(k == 0))] for k, (lo, hi) in enumerate(_shares(opts.worlds, opts.subscribers))],
        reserved,
    )
    while not periods:  # warp compiles its kernels in the first period: warm up after it
        time.sleep(0.1)
    began = time.time()
    while time.time() - began < opts.warmup:
        time.sleep(0.1)
    start = 0.0
    goals = (
        Children(
            [["--goals", str(opts.domain), str(lo), str(hi), opts.goals, str(opts.goal_rate), "0"] for lo, hi in _shares(opts.worlds, opts.goal_clients)],
            reserved,
        )
        if opts.goals != "none"
        else None
    )
    if goals is not None:  # discovery first (clients and the servers they call into being), then one start for all
        asked = time.time()
        while time.time() - asked < 180 and sum(1 for lines in goals.lines for line in list(lines) if line[0] == "ready") < len(goals.procs):
            time.sleep(0.1)
        ready = [line for lines in goals.lines for line in list(lines) if line[0] == "ready"]
        found = sum(int(line[2]) for line in ready)
        discovery = [(p, ph) for (t, p), ph in zip(periods, phases, strict=False) if asked <= t]
        d = np.array([p for p, _ in discovery] or [float("nan")]) * 1e3
        if discovery:  # where the worst period of discovery went
            p, ph = max(discovery, key=lambda x: x[0])
            print(f"  discovery's worst: {p * 1e3:.1f} ms = " + ", ".join(f"{k} {v * 1e3:.1f}" for k, v in sorted(ph.items(), key=lambda x: -x[1])))
        print(f"discovery: {len(ready)} of {len(goals.procs)} goal clients ready, {found} of {opts.worlds} action servers "
              f"found, in {time.time() - asked:.1f} s; loop period meanwhile {np.median(d):.2f} ms median, "
              f"{d.max():.2f} ms worst")  # fmt: skip
        # a client that found its server may not be matched by it yet (the server's response
        # writer waits for the client's reader, then drops the answer: rmw_fastrtps's "failed
        # to send response (timeout)"): let discovery settle both ways before the burst
        start = time.time() + opts.settle
        goals.tell(f"go {start:.3f}")
    t0 = max(time.time(), start) + (0.0 if goals is not None else 0.5)
    t1 = t0 + opts.seconds
    sim0 = None
    while time.time() < t1:
        if sim0 is None and time.time() >= t0:
            sim0 = loop.sim_time
        time.sleep(0.05)
    sim1 = loop.sim_time
    counted = _counted(subs, t1) - _counted(subs, t0)
    first_period = periods[0][0] - periods[0][1]
    heard_at = _all_heard(subs, _shares(opts.worlds, opts.subscribers))
    if goals is not None:
        deadline = time.time() + opts.result_timeout
        while opts.goals == "burst" and time.time() < deadline:
            sent = sum(int(line[2]) for lines in goals.lines for line in list(lines) if line[0] == "sent")
            results = sum(1 for lines in goals.lines for line in list(lines) if line[0] == "result")
            if sent and results >= sent:
                break
            time.sleep(0.1)
        goals.close()  # no more goals; the clients wait for those in flight, the loop still running
    stop.set()
    loop.stop()
    runner.join(timeout=10)
    subs.close()
    window = [p for t, p in periods if t0 <= t <= t1]
    budget = 1.0 / opts.control_rate
    rtf = (sim1 - sim0) / opts.seconds if sim0 is not None else float("nan")
    wall = t1 - t0
    expected = opts.worlds * opts.control_rate * rtf
    print(f"# {platform.node() or 'host'}, {os.cpu_count()} cores, Python {platform.python_version()}, {_versions()}, "
          f"{opts.backend} {opts.model}, {opts.worlds} worlds, control {opts.control_rate:g} Hz, {nworker} bridge workers, "
          f"{opts.subscribers} subscriber processes, loop thread {_policy(opts.thread_priority, opts)}, "
          f"load {os.getloadavg()[0]:.1f}, {time.strftime('%Y-%m-%d')}")  # fmt: skip
    p = np.array(window or [float("nan")]) * 1e3  # no period in the window: say so with NaN
    over = [(d, ph) for (t, d), ph in zip(periods, phases, strict=False) if t0 <= t <= t1 and d > 1.0 / opts.control_rate]
    for d, ph in sorted(over, key=lambda x: -x[0])[:5]:  # where the worst periods' time went
        print(f"  over budget: {d * 1e3:.1f} ms = " + ", ".join(f"{k} {v * 1e3:.1f}" for k, v in sorted(ph.items(), key=lambda x: -x[1])))
    print(f"  periods over budget: {len(over)} of {len(window)}")
    full = [d * 1e3 for g, t, d in collections if g == 2]
    print(f"  gc generation 2 over the whole run: {len(full)} collections" + (f", longest {max(full):.1f} ms" if full else ""))
    in_window = [(g, d) for g, t, d in collections if t0 <= t <= t1]
    for g in range(3):
        ds = [d * 1e3 for gen, d in in_window if gen == g]
        if ds:
            print(f"  gc generation {g}: {len(ds)} collections in the window, longest {max(ds):.1f} ms")
    print(f"RTF held {rtf:.3f} over {wall:.1f} s; loop period {np.median(p):.2f} ms median, {p.max():.2f} ms worst, "
          f"{np.percentile(p, 99):.2f} ms p99 (budget {budget * 1e3:.1f} ms, {len(p)} periods)")  # fmt: skip
    print(f"joint_states received {counted[0] / wall:,.0f}/s of {expected:,.0f}/s expected ({counted[0] / wall / expected:.3f})")
    print(f"tf (/<ns>/tf) received {counted[1] / wall:,.0f}/s of {expected:,.0f}/s expected ({counted[1] / wall / expected:.3f})")
    print(f"every world heard (joint_states and /<ns>/tf) {heard_at - first_period:.1f} s after the loop's first period"
          if heard_at is not None else f"not every world heard: {_heard(subs)} of {opts.worlds} (joint_states, tf)")  # fmt: skip
    fleet_expected = nworker * opts.control_rate * rtf
    print(f"tf (/tf, {nworker} worker messages per period) received {counted[2] / wall:,.0f}/s of {fleet_expected:,.0f}/s expected")
    if goals is not None:
        sent_lines = [line for lines in goals.lines for line in list(lines) if line[0] == "sent"]
        results = [line for lines in goals.lines for line in list(lines) if line[0] == "result"]
        sent = sum(int(line[2]) for line in sent_lines)
        statuses: dict[str, int] = {}
        for line in results:
            key = line[2] if line[2] != "6" else f"6 ({line[3]})"
            statuses[key] = statuses.get(key, 0) + 1
        first = min((float(line[1]) for line in sent_lines), default=float("nan"))
        last = max((float(line[1]) for line in results), default=float("nan"))
        names = {"4": "SUCCEEDED", "5": "CANCELED", "rejected": "rejected"}
        by = ", ".join(f"{names.get(k, k.replace('6 (', 'ABORTED (error_code '))} {v}" for k, v in sorted(statuses.items()))
        print(f"goals: {opts.goals}, sent {sent}, results {len(results)} ({by}); first sent to last result {last - first:.2f} s")
        if opts.verbose:
            for line in results:
                print(" ".join(line))
    host.close()
    sim.shutdown()
    if opts.capacity:
        capacity(opts)


def _policy(priority: int, opts: argparse.Namespace) -> str:
    """What the loop thread asked for (granted or not: the loop warns when not), for the header."""
    text = f"asked SCHED_FIFO {priority}" if priority else "normal policy"
    if opts.cpu_affinity:
        text += f", on cores {','.join(map(str, opts.cpu_affinity))}" + (" (reserved)" if opts.reserve_loop_cores else "")
    return text


def capacity(opts: argparse.Namespace) -> None:
    k = opts.subscribers
    seconds = 5.0
    kids = Children(
        [["--cap-pub", str(opts.domain + 1), str(i), str(seconds)] for i in range(k)]
        + [["--cap-sub", str(opts.domain + 1), str(i), str(seconds)] for i in range(k)]
    )
    for p in kids.procs:
        p.wait(timeout=60)
    time.sleep(0.2)
    published = sum(int(line[1]) for lines in kids.lines for line in lines if line[0] == "published")
    received = sum(int(line[1]) for lines in kids.lines for line in lines if line[0] == "received")
    print(f"plain rclpy capacity: {k} publisher + {k} subscriber processes, Float64MultiArray: "
          f"{published / seconds:,.0f} published/s, {received / seconds:,.0f} received/s")  # fmt: skip


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--subscriber":
        subscriber(int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5] == "1")
        return
    if len(sys.argv) > 1 and sys.argv[1] == "--goals":
        goal_client(int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5], float(sys.argv[6]), float(sys.argv[7]))
        return
    if len(sys.argv) > 1 and sys.argv[1] in ("--cap-pub", "--cap-sub"):
        fn = publisher_pair if sys.argv[1] == "--cap-pub" else capacity_subscriber
        fn(int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]))
        return
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", choices=sorted(PRESETS), default=None)
    p.add_argument("--backend", default="cpu")
    p.add_argument("--model", default="arm")
    p.add_argument("--worlds", type=int, default=16)
    p.add_argument("--control-rate", type=float, default=100.0)
    p.add_argument("--subscribers", type=int, default=1, help="subscriber processes")
    p.add_argument("--goal-clients", type=int, default=1, help="goal client processes")
    p.add_argument("--goals", choices=("none", "burst", "rate"), default="rate")
    p.add_argument("--goal-rate", type=float, default=1.0, help="rate: goals per world per second")
    p.add_argument("--bridge-workers", type=int, default=None)
    p.add_argument("--devices", default=None, help="mjx/warp: spread the worlds over these GPUs ('all', '0,1'), one process each")
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--warmup", type=float, default=3.0)
    p.add_argument("--result-timeout", type=float, default=30.0)
    p.add_argument("--capacity", action="store_true", help="also measure plain rclpy's capacity on this host")
    p.add_argument("--domain", type=int, default=88)
    p.add_argument("--verbose", action="store_true", help="every goal's result")
    p.add_argument("--worker-nice", type=int, default=0, help="renice the bridge workers by this much (they yield to the loop)")
    p.add_argument("--threads", type=int, default=None, help="cpu backend: step threads, the loop's included (default: every core)")
    p.add_argument("--thread-priority", type=int, default=50, help="the loop thread's SCHED_FIFO priority, as the command's (0: normal policy)")
    p.add_argument("--cpu-affinity", type=lambda t: tuple(int(c) for c in t.split(",")), default=(), help="the loop thread's cores (the bridge workers then keep off them)")
    p.add_argument("--reserve-loop-cores", action="store_true", help="this script's subscribers and goal clients keep off the loop's cores too, as a user's taskset would")
    p.add_argument("--gc-freeze", action="store_true", help="gc.freeze() before the loop starts (a paced loop with a thread priority or cores does it itself from its second period)")
    p.add_argument("--settle", type=float, default=5.0, help="s between every goal client's ready and the burst")
    opts = p.parse_args()
    if opts.preset:
        preset = PRESETS[opts.preset]
        for key, flag in (("backend", "--backend"), ("worlds", "--worlds"), ("subscribers", "--subscribers"),
                          ("goal_clients", "--goal-clients"), ("goals", "--goals"), ("goal_rate", "--goal-rate")):  # fmt: skip
            if flag not in sys.argv:
                setattr(opts, key, preset[key])
        if "--control-rate" not in sys.argv:
            opts.control_rate = preset["control"]
    run(opts)


if __name__ == "__main__":
    main()
