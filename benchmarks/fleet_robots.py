"""Several robots in one world (batchsim.fleet): what sharing a world costs, and a warehouse over ROS 2.

    .venv/bin/python benchmarks/fleet_robots.py physics --backend cpu --robots 8 --total 128
    .venv/bin/python benchmarks/fleet_robots.py ros --worlds 16 --rate 50 --seconds 20

physics: a world of K robots against K worlds of one robot, the same total robots on the same
backend in one run, both composed from fleet files (one floor, the robot's own scene left out),
in interleaved rounds (the best of each shown), each through the contract (`write(); step(nstep)` in a loop, read every
period): robot-steps/s = worlds x K x steps / s, and their ratio. The robots stand on a grid 3 m
apart, so contacts between robots are few (the case the issue's >= 0.8 goal is for); `--model`
picks the robot (rover: contacts with the floor, arm: none). On a GPU backend the first
periods compile and are not timed.

ros: `batchsim --fleet FILE --worlds N --rtf 1 --publish-rate R` (default the warehouse) in a
process of its own on a private ROS domain (discovery on this host only), and subscriber
processes (`--subscriber-processes`, each a share of the worlds) that count, raw, every robot's joint_states, the odom (the simulation's ground truth)
of every robot with a floating base, and every world's tf: received against what the fleet
published in the window (worlds x robots x rate x the sim time the window spanned, from /clock
as the subscriber heard it), over a window of wall seconds after a warm-up; the RTF held is
the status line's, once a second (median and worst). Nothing is asserted: speed is measured here, never in tests.
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import os
import platform
import re
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
# fleet.py's: the subscriber's executor, the child processes' PYTHONPATH, the versions line
from fleet import LOCALHOST, _pythonpath, _versions, executor_until_stdin_closes  # noqa: E402

# --- physics: K robots in a world against K worlds of one ---
_ENVIRONMENT = """<mujoco model="floor">
  <option timestep="{timestep}" integrator="{integrator}" solver="{solver}"/>
  <worldbody>
    <light name="sun" pos="0 0 5" dir="0 0 -1" directional="true"/>
    <geom name="floor" type="plane" size="0 0 0.05"/>
  </worldbody>
</mujoco>
"""


def solver_environment(model: str, solver: str, folder: Path) -> Path:
    """A floor whose physics options are the robot's own but for the constraint solver (a fleet's
    environment sets the options every robot of a world steps with): its path, written in `folder`."""
    import mujoco

    import batchsim

    m = batchsim.load(model).mjmodel
    integrator = {0: "Euler", 1: "RK4", 2: "implicit", 3: "implicitfast"}[int(m.opt.integrator)]
    path = folder / f"floor_{solver.lower()}.xml"
    path.write_text(_ENVIRONMENT.format(timestep=m.opt.timestep, integrator=integrator, solver=solver))
    assert mujoco.MjModel.from_xml_path(str(path)).opt.solver == {"PGS": 0, "CG": 1, "NEWTON": 2}[solver.upper()]
    return path


def fleet_of(model: str, k: int, spacing: float = 3.0, environment: Path | None = None) -> dict:
    columns = max(1, int(np.ceil(np.sqrt(k))))
    return {
        **({"environment": str(environment)} if environment is not None else {}),
        "robots": [
            {"name": "r_{k}", "model": model, "count": k, "grid": {"spacing": [spacing, spacing], "columns": columns}}
        ]
        if k > 1
        else [{"name": "r_1", "model": model}]
    }


def robot_steps_per_second(sim, robots: int, nstep: int, seconds: float, warmup: int) -> tuple[float, float, float]:
    """(robot-steps/s, median period ms, worst period ms) of write/step/read, flat out."""
    for _ in range(warmup):  # a GPU backend compiles (mjx) or captures (warp) here
        sim.write()
        sim.step(nstep)
        sim.read()
    periods = []
    start = time.perf_counter()
    while time.perf_counter() - start < seconds:
        t = time.perf_counter()
        sim.write()
        sim.step(nstep)
        sim.read()
        periods.append(time.perf_counter() - t)
    elapsed = sum(periods)
    rate = sim.nworld * robots * nstep * len(periods) / elapsed
    return rate, 1e3 * statistics.median(periods), 1e3 * max(periods)


def physics(opts: argparse.Namespace) -> None:
    import batchsim

    environment = None
    if opts.solver is not None:  # both layouts on a floor whose options set the solver
        environment = solver_environment(opts.model, opts.solver, Path(tempfile.mkdtemp()))
    print(
        f"# {_machine()}; {_versions()}; backend {opts.backend}, model {opts.model}, {opts.total} robots in all, "
        f"best of {opts.rounds} interleaved rounds; solver {opts.solver or 'as the model sets it'}"
    )
    print(f"{'layout':28s} {'worlds':>6s} {'robots/world':>12s} {'robot-steps/s':>14s} {'median ms':>10s} {'worst ms':>9s}")
    for k in opts.robots:
        nworld = max(1, opts.total // k)
        # both layouts composed alike (the default floor, the robot's own scene left out), so
        # the only difference is whether the robots share worlds
        layouts = [(f"{nworld} worlds x {k} robots", nworld, k), (f"{nworld * k} worlds x 1 robot", nworld * k, 1)]
        sims = {}
        for _, n, per in layouts:
            sims[per] = batchsim.make(fleet_of(opts.model, per, environment=environment), n, opts.backend)
            sims[per].configure()
            sims[per].activate()
        best: dict[int, tuple[float, float, float]] = {}
        for _ in range(opts.rounds):
            for _, _, per in layouts:
                found = robot_steps_per_second(sims[per], per, opts.nstep, opts.seconds, opts.warmup)
                if per not in best or found[0] > best[per][0]:
                    best[per] = found
        for label, n, per in layouts:
            rate, median, worst = best[per]
            print(f"{label:28s} {n:6d} {per:12d} {rate:14.0f} {median:10.3f} {worst:9.3f}", flush=True)
            sims[per].shutdown()
        print(f"ratio {k} robots a world / 1 robot a world: {best[k][0] / best[1][0]:.3f}", flush=True)


# --- ros: the warehouse, every robot's topics counted in another process ---
def subscriber(domain: int, first: int, worlds: int, robot_names: str, odom_names: str, depth: int, rate: float) -> None:
    """Count, for worlds first .. first + worlds - 1, every robot's joint_states, the odom of those
    with a floating base, and every world's tf, raw; print `count <wall> <joint_states> <odom> <tf>
    <sim time>` (the newest /clock) every 0.25 s and `heard <wall>` once every topic was heard,
    until stdin closes; then `stamps <kind> <json>`: how many of each kind came with each stamp
    (in publish periods, round(stamp x rate)), read from the CDR bytes."""
    robots, with_odom = robot_names.split(","), [n for n in odom_names.split(",") if n]
    os.environ.update(LOCALHOST)
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.context import Context
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import JointState
    from tf2_msgs.msg import TFMessage

    context = Context()
    rclpy.init(context=context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    node = Node("fleet_robots_benchmark", context=context)
    counts = {
        "js": np.zeros(worlds * len(robots), np.int64),
        "odom": np.zeros(worlds * len(with_odom), np.int64),
        "tf": np.zeros(worlds, np.int64),
    }

    stamps = {kind: collections.Counter() for kind in counts}
    # the header's stamp: after the 4-byte CDR encapsulation; a TFMessage's first transform's, after its length
    offset = {"js": 4, "odom": 4, "tf": 8}

    def counter(kind: str, k: int):
        bins, at = stamps[kind], offset[kind]

        def callback(msg: bytes) -> None:
            counts[kind][k] += 1
            sec, nsec = struct.unpack_from("<iI", msg, at)
            bins[round((sec + nsec * 1e-9) * rate)] += 1

        return callback

    clock = [0.0]

    def on_clock(msg: Clock) -> None:
        clock[0] = max(clock[0], msg.clock.sec + msg.clock.nanosec * 1e-9)

    node.create_subscription(Clock, "/clock", on_clock, 10)
    for i, w in enumerate(range(first, first + worlds)):
        node.create_subscription(TFMessage, f"/world_{w}/tf", counter("tf", i), max(100, depth), raw=True)
        for r, name in enumerate(robots):
            node.create_subscription(JointState, f"/world_{w}/{name}/joint_states", counter("js", i * len(robots) + r), depth, raw=True)
        for r, name in enumerate(with_odom):
            node.create_subscription(Odometry, f"/world_{w}/{name}/odom", counter("odom", i * len(with_odom) + r), depth, raw=True)
    executor, stop = executor_until_stdin_closes(context, node)
    heard, next_report = False, time.time()
    while not stop.is_set():
        executor.spin_once(timeout_sec=0.05)
        now = time.time()
        if not heard and all(c.all() for c in counts.values() if c.size):
            heard = True
            print(f"heard {now:.3f}", flush=True)
        if now >= next_report:
            next_report = now + 0.25
            print(f"count {now:.3f} {counts['js'].sum()} {counts['odom'].sum()} {counts['tf'].sum()} {clock[0]:.6f}", flush=True)
    for kind, bins in stamps.items():
        print(f"stamps {kind} {json.dumps(bins)}", flush=True)
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown(context=context)


def _lines(proc: subprocess.Popen, sink: list[str]) -> threading.Thread:
    def read() -> None:
        for line in proc.stdout:
            sink.append(line.rstrip("\n"))

    t = threading.Thread(target=read, daemon=True)
    t.start()
    return t


def ros(opts: argparse.Namespace) -> None:
    from batchsim.fleet import load_fleet

    spec = load_fleet(opts.fleet)
    names = [r.name for r in spec.robots]
    with_odom = [r.name for r in spec.robots if r.floating_base is not None]
    env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(opts.domain), "PYTHONPATH": _pythonpath()}
    print(
        f"# {_machine()}; {_versions()}; {opts.fleet}: {opts.worlds} worlds x {len(names)} robots on {opts.backend}, "
        f"publish {opts.rate:g} Hz"
    )
    nsub = max(1, min(opts.subscriber_processes, opts.worlds))
    firsts = [opts.worlds * i // nsub for i in range(nsub + 1)]  # each process a contiguous share of the worlds
    subs = [
        subprocess.Popen(
            [sys.executable, __file__, "--subscriber", str(opts.domain), str(a), str(b - a), ",".join(names), ",".join(with_odom), str(opts.depth), str(opts.rate)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env,
        )  # fmt: skip
        for a, b in zip(firsts[:-1], firsts[1:], strict=True)
    ]
    sub_lines: list[list[str]] = [[] for _ in subs]
    readers = [_lines(sub, lines) for sub, lines in zip(subs, sub_lines, strict=True)]
    fleet = subprocess.Popen(
        [
            sys.executable, "-m", "batchsim.cli", "--fleet", str(opts.fleet),
            "--worlds", str(opts.worlds), "--rtf", "1", "--publish-rate", str(opts.rate), "--status-every", "1",
            "--backend", opts.backend, *opts.extra,
        ],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    fleet_lines: list[str] = []
    t = threading.Thread(target=lambda: [fleet_lines.append(x.rstrip("\n")) for x in fleet.stderr], daemon=True)
    t.start()
    started = None
    deadline = time.time() + 300
    while started is None and time.time() < deadline:
        if fleet.poll() is not None:
            raise SystemExit("batchsim ended:\n" + "\n".join(fleet_lines[-20:]))
        if any(line.startswith(f"batchsim: {opts.worlds} x ") for line in fleet_lines):
            started = time.time()
        time.sleep(0.1)
    heard = None
    while heard is None and time.time() < started + 120:
        each = [next((float(x.split()[1]) for x in lines if x.startswith("heard ")), None) for lines in sub_lines]
        heard = None if None in each else max(each)
        time.sleep(0.1)
    time.sleep(opts.warmup)
    n0 = len(fleet_lines)
    c0 = [_last_count(lines) for lines in sub_lines]
    time.sleep(opts.seconds)
    c1 = [_last_count(lines) for lines in sub_lines]
    rtfs = [float(m.group(1)) for x in fleet_lines[n0:] if (m := re.search(r"rtf\s+([0-9.]+)", x))]
    fleet.send_signal(2)
    fleet.wait(30)
    for sub in subs:
        sub.stdin.close()
        sub.wait(30)
    for reader in readers:  # their last lines, the stamps, read
        reader.join(10)
    # each process's own window: its counts against what its worlds published in the sim time it spanned
    window = statistics.mean(b[0] - a[0] for a, b in zip(c0, c1, strict=True))
    sim_window = statistics.mean(b[4] - a[4] for a, b in zip(c0, c1, strict=True))  # from /clock as the subscribers heard it
    rtf = statistics.median(rtfs) if rtfs else float("nan")
    print(f"heard every robot's joint_states, odom and tf {heard - started:.1f} s after the start line" if heard else "not every topic was heard")
    print(f"rtf held: median {rtf:.3f}, worst second {min(rtfs) if rtfs else float('nan'):.3f} ({len(rtfs)} status lines); "
          f"{sim_window:.2f} sim s in the {window:.2f} s window")  # fmt: skip
    kinds = (("joint_states", len(names)), ("odom", len(with_odom)), ("tf", 1))  # per world
    print(f"{nsub} subscriber process{'es' if nsub > 1 else ''}")
    for k, (name, per_world) in enumerate(kinds):
        if not per_world:
            continue
        got = sum(b[k + 1] - a[k + 1] for a, b in zip(c0, c1, strict=True))
        # what the fleet published in the sim time each window spanned
        expected = sum(per_world * (n1 - n0) * opts.rate * (b[4] - a[4]) for n0, n1, a, b in zip(firsts[:-1], firsts[1:], c0, c1, strict=True))
        # by stamp: of every message the fleet published in the window's publish periods (the
        # last second left out: still on its way when the window closed), how many arrived
        first_bin, last_bin = math.ceil(max(a[4] for a in c0) * opts.rate), math.floor((min(b[4] for b in c1) - 1.0) * opts.rate)
        kind = ("js", "odom", "tf")[k]
        arrived = sum(n for lines in sub_lines for x in lines if x.startswith(f"stamps {kind} ")
                      for b, n in json.loads(x.split(" ", 2)[2]).items() if first_bin <= int(b) <= last_bin)  # fmt: skip
        sent = per_world * opts.worlds * (last_bin - first_bin + 1)
        print(f"{name:12s} received {got / window:9.0f}/s of {expected / window:9.0f}/s published ({got / expected:.4f}); "
              f"by stamp {arrived} of {sent} ({arrived / sent:.4f})")  # fmt: skip


def _last_count(lines: list[str]) -> tuple[float, int, int, int, float]:
    for x in reversed(lines):
        if x.startswith("count "):
            _, t, js, odom, tf, clock = x.split()
            return float(t), int(js), int(odom), int(tf), float(clock)
    raise SystemExit("the subscriber reported nothing")


def _machine() -> str:
    return f"{platform.node()} {os.cpu_count()} cores, {platform.processor() or platform.machine()}, {time.strftime('%Y-%m-%d')}"


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--subscriber":
        subscriber(int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5], sys.argv[6], int(sys.argv[7]), float(sys.argv[8]))
        return
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="what", required=True)
    ph = sub.add_parser("physics")
    ph.add_argument("--backend", default="cpu")
    ph.add_argument("--model", default="rover")
    ph.add_argument("--robots", type=lambda s: [int(x) for x in s.split(",")], default=[4, 8], help="robots per world, comma-separated")
    ph.add_argument("--total", type=int, default=128, help="robots in all")
    ph.add_argument("--nstep", type=int, default=5, help="physics steps per control period")
    ph.add_argument("--seconds", type=float, default=3.0, help="each round's length")
    ph.add_argument("--rounds", type=int, default=3, help="interleaved rounds per layout (the best is shown)")
    ph.add_argument("--warmup", type=int, default=5)
    ph.add_argument("--solver", choices=["Newton", "CG", "PGS"], help="every world's constraint solver (default: the model's)")
    r = sub.add_parser("ros")
    r.add_argument("--fleet", default=str(ROOT / "examples/fleets/warehouse.yaml"))
    r.add_argument("--worlds", type=int, default=16)
    r.add_argument("--rate", type=float, default=50.0, help="publish rate, Hz")
    r.add_argument("--backend", default="cpu")
    r.add_argument("--seconds", type=float, default=20.0)
    r.add_argument("--warmup", type=float, default=5.0)
    r.add_argument("--domain", type=int, default=73)
    r.add_argument("--depth", type=int, default=10, help="the subscribers' QoS depth (the fleet's: -- --qos-depth N)")
    r.add_argument("--subscriber-processes", type=int, default=1, help="the worlds split over this many subscribers")
    r.add_argument("extra", nargs="*", help="more batchsim flags, after --")
    opts = p.parse_args()
    physics(opts) if opts.what == "physics" else ros(opts)


if __name__ == "__main__":
    main()
