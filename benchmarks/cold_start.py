"""Cold start on a GPU host: `batchsim --model rover --worlds N --backend warp` from an empty Warp
kernel cache, every world's camera, depth image and lidar subscribed before it starts.

Issue 24 found that run compiling for 156 s and then standing still ~26 s at the first camera and
lidar request (sim 0.01 s, rtf 0.00): the render and ray kernels compiled on first use, after the
first status line. This prints, with the wall time since the process started:

  - every start-up line up to the first status line (the compile stage among them);
  - each status line of the first --seconds after it (sim time, RTF);
  - when the subscribers got their first image and first scan;
  - images and scans received per wall second in the windows after the first status line;
  - the camera and lidar samples the bridge's workers never got (`missed <topic>` in /diagnostics);

and ends with one verdict line: whether the fleet ran from its first status line (sim time
advancing in every status line, images and scans arriving within --first-within seconds of it).
A subscriber or batchsim that dies fails the run (sensors.HelperDied), as in sensors.py.

    python3 benchmarks/cold_start.py [--worlds 1024] [--seconds 20] [--subscribers 4] [--keep-cache]

--keep-cache runs with the kernel cache as it is (the warm start, for comparison).
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fleet import Batchsim, listen_to_diagnostics  # noqa: E402
from sensors import LOCALHOST, MODEL, Helper, HelperDied, check_batchsim, subscriber_command, subscriber_env  # noqa: E402

STATUS = re.compile(r"sim\s+([0-9.]+) s \| rtf\s+([0-9.]+)")  # a status line (the start line names an rtf too)


def counts_at(samples: list[tuple[float, tuple[int, ...]]], at: float) -> np.ndarray:
    before = [c for t, c in samples if t <= at]
    return np.array(before[-1] if before else (0, 0, 0), dtype=float)


def first(samples: list[list[tuple[float, tuple[int, ...]]]], kind: int) -> float | None:
    """The wall time at which any subscriber first reported a message of `kind` (0 image, 2 scan)."""
    times = [t for s in samples for t, c in s if c[kind] > 0]
    return min(times) if times else None


def missed_listener(domain: int) -> None:
    """Print `missed <worker> <topic>=<n> ...` for every /diagnostics message: its worlds'
    `missed <camera or lidar topic>` counts summed (ros_bridge/worker/diagnostics.py), until
    stdin closes."""

    def callback(msg) -> None:
        sums: dict[str, int] = {}
        for status in msg.status:
            for kv in status.values:
                if kv.key.startswith("missed ") and kv.key != "missed joint_states":
                    sums[kv.key[7:]] = sums.get(kv.key[7:], 0) + int(kv.value)
        if msg.status:
            worker = msg.status[0].hardware_id
            print(f"missed {worker} " + " ".join(f"{k}={v}" for k, v in sorted(sums.items())), flush=True)

    listen_to_diagnostics(domain, "cold_start_missed", callback)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--missed-listener"]:
        missed_listener(int(argv[1]))
        return 0
    try:
        return run(argv)
    except HelperDied as e:  # one line, naming who died and why, and a failed run
        print(f"cold_start.py: {e}", file=sys.stderr, flush=True)
        return 1


def run(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--worlds", type=int, default=1024)
    p.add_argument("--seconds", type=float, default=20.0, help="watched after the first status line")
    p.add_argument("--subscribers", type=int, default=4, help="subscriber processes, the worlds split among them")
    p.add_argument("--first-within", type=float, default=3.0, help="s after the first status line for the first image and scan")
    p.add_argument("--keep-cache", action="store_true", help="keep Warp's kernel cache (a warm start)")
    p.add_argument("--domain", type=int, default=int(os.environ.get("ROS_DOMAIN_ID", "57")))
    args = p.parse_args(argv)
    os.environ.update(LOCALHOST)
    os.environ["ROS_DOMAIN_ID"] = str(args.domain)
    cache = None
    if not args.keep_cache:  # Warp compiles every kernel again: batchsim's, MuJoCo Warp's, the sensors'
        cache = tempfile.TemporaryDirectory(prefix="warp-cold-")
        os.environ["WARP_CACHE_PATH"] = cache.name
    n, k = args.worlds, max(1, min(args.subscribers, args.worlds))
    edges = [round(i * n / k) for i in range(k + 1)]
    env = subscriber_env()
    helpers = [Helper(f"subscriber {i}", subscriber_command(args.domain, a, b), env) for i, (a, b) in enumerate(zip(edges[:-1], edges[1:], strict=True))]
    listener = Helper("the /diagnostics listener", [sys.executable, __file__, "--missed-listener", str(args.domain)], env)
    missed: dict[str, dict[str, int]] = {}  # per worker (its first world): topic -> samples missed, its last report

    def listen() -> None:
        for line in listener.proc.stdout:
            parts = line.split()
            if parts[:1] == ["missed"] and len(parts) >= 2:
                missed[parts[1]] = {k: int(v) for k, _, v in (p.partition("=") for p in parts[2:])}

    threading.Thread(target=listen, daemon=True).start()
    samples: list[list[tuple[float, tuple[int, ...]]]] = [[] for _ in helpers]

    def read(i: int) -> None:
        for line in helpers[i].proc.stdout:
            parts = line.split()
            if parts and parts[0] == "count":
                samples[i].append((float(parts[1]), tuple(int(x) for x in parts[2:5])))

    for i in range(len(helpers)):
        threading.Thread(target=read, args=(i,), daemon=True).start()
    print(f"cold start: {MODEL}, {n} worlds, warp, kernel cache {'kept' if cache is None else 'empty: ' + cache.name}; "
          f"{k} subscriber processes take every world's image, depth image and scan", flush=True)  # fmt: skip
    try:
        while not all(samples):  # subscribed before batchsim starts, as in the issue
            for h in helpers:
                h.check()
            time.sleep(0.05)
        t0 = time.time()
        b = Batchsim(["--model", MODEL, "--worlds", str(n), "--backend", "warp"], args.domain)
        try:
            deadline = t0 + 900.0
            while not b.status(0.0, float("inf")):
                check_batchsim(b)
                if time.time() > deadline:
                    raise HelperDied("batchsim printed no status line in 900 s")
                time.sleep(0.1)
            running = min(t for t, line in b.lines if STATUS.search(line))
            time.sleep(args.seconds)
            for h in helpers:
                h.check()
            check_batchsim(b)
        finally:
            b.stop()
    finally:
        for h in [*helpers, listener]:
            try:
                h.proc.stdin.close()
            except OSError:
                pass
        for h in [*helpers, listener]:
            h.proc.wait(timeout=20)
        if cache is not None:
            cache.cleanup()
    for t, line in b.lines:
        if t <= running + args.seconds:
            print(f"{t - t0:7.1f} s  {line}")
    sims = [(t, float(m.group(1))) for t, line in b.lines if (m := STATUS.search(line)) and t <= running + args.seconds]
    still = [f"{t - t0:.1f} s" for (t, s), (_, s0) in zip(sims[1:], sims[:-1], strict=False) if s <= s0]
    # a stall under a moving clock: the loop paced at RTF 1 that ran at less than half of it
    slow = [f"{t - t0:.1f} s (rtf {float(m.group(2)):.2f})" for t, line in b.lines
            if (m := STATUS.search(line)) and t <= running + args.seconds and float(m.group(2)) < 0.5]  # fmt: skip
    image, scan = first(samples, 0), first(samples, 2)
    print(f"first status line {running - t0:.1f} s after the start")
    for name, at in (("image", image), ("scan", scan)):
        print(f"first {name}: " + ("never" if at is None else f"{at - t0:.1f} s after the start, {at - running:+.1f} s from the first status line"))
    total = lambda at: sum(counts_at(s, at) for s in samples)  # noqa: E731
    end = args.seconds - 0.5  # the subscribers' last reports lag a little
    edges_s = [e for e in (0.0, 2.0, 5.0, 10.0, 20.0, 40.0) if e < end] + [end]
    for a, z in zip(edges_s[:-1], edges_s[1:], strict=False):
        got = (total(running + z) - total(running + a)) / (z - a)
        print(f"  {a:4.1f}-{z:4.1f} s after it: {got[0]:9,.0f} images/s, {got[1]:9,.0f} depth images/s, {got[2]:9,.0f} scans/s received")
    lost: dict[str, int] = {}
    for counts in missed.values():
        for topic, n in counts.items():
            lost[topic] = lost.get(topic, 0) + n
    print(f"missed at the workers by the end (/diagnostics, {len(missed)} workers heard): "
          + (", ".join(f"{topic} {n:,}" for topic, n in sorted(lost.items())) or "none"))  # fmt: skip
    late = [name for name, at in (("image", image), ("scan", scan)) if at is None or at - running > args.first_within]
    ok = not still and not late and not slow
    print(("RAN FROM ITS FIRST STATUS LINE" if ok else "DID NOT RUN FROM ITS FIRST STATUS LINE")
          + (f": sim time stood still at {', '.join(still)}" if still else "")
          + (f"; under half of real time at {', '.join(slow)}" if slow else "")
          + (f"; no first {' or '.join(late)} within {args.first_within:g} s of it" if late else ""))  # fmt: skip
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
