"""Recording at full rate: does it slow the loop, and does every message reach the file?

    .venv/bin/python benchmarks/recording.py --repeat 3           # 16 arms at 1 kHz, 20 s, off then on, 3 times
    .venv/bin/python benchmarks/recording.py --worlds 1024 --backend warp --control-rate 100

The loop runs in this process as `batchsim` runs it (the arm's default controllers, the ROS 2
bridge with its workers in processes, RTF 1, the loop thread's SCHED_FIFO where allowed), once
without a recording and once with `--record --no-record-inputs` (the default topic set: joint_states,
wrist_ft_broadcaster/wrench, /tf, /tf_static, /clock, robot_description), and once with `--record`
(the same, and the physics inputs `batchsim resim` re-runs from: /batchsim/inputs, /batchsim/starts). Reported per run:
the RTF held (sim time over wall time from the first period to the last), the loop's own
time per period (the pacing sleep excluded: median, 99th percentile, worst) against the
period's budget; with the recording, the messages in the file counted per topic against what
the periods that ran must have given (every world's state topics every period, /clock and
/tf every period), the periods the ring dropped, and the file's bytes per world and sim second.
Nothing is asserted.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # its siblings

from paced_fleet import paced_fleet, timed_run  # noqa: E402


def run(opts: argparse.Namespace, path: str | None, inputs: bool = True) -> dict:
    from ros_bridge.bridge import BridgeOptions
    from ros_bridge.options import RecordOptions

    with paced_fleet(opts, BridgeOptions(record=RecordOptions(path, inputs=inputs))) as (_sim, loop, host):
        figures = timed_run(loop)
        figures["dropped"] = int(host.memory["rec.dropped"][0]) if path else 0
    return figures


def count(path: str) -> Counter:
    from mcap.reader import make_reader

    topics: Counter = Counter()
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    for channel_id, n in summary.statistics.channel_message_counts.items():
        topic = summary.channels[channel_id].topic
        topics[topic if not topic.startswith("/world_") else topic.split("/", 2)[2]] += n
    return topics


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--worlds", type=int, default=16)
    p.add_argument("--model", default="arm")
    p.add_argument("--backend", default="cpu")
    p.add_argument("--control-rate", type=float, default=1000.0)
    p.add_argument("--duration", type=float, default=20.0, help="sim seconds per run")
    p.add_argument("--repeat", type=int, default=1, help="runs of each, alternating (a shared machine's load drifts)")
    p.add_argument("--domain", type=int, default=91)
    p.add_argument("--devices", default=None, help="mjx/warp: spread the worlds over these GPUs ('all', '0,1')")
    p.add_argument("--warmup", action="store_true", help="one untimed 1 s fleet first (warp compiles and captures)")
    opts = p.parse_args()
    os.environ.update({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": str(opts.domain)})
    import mcap
    import mujoco

    print(f"# {platform.node()}: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
          f"Python {platform.python_version()}, MuJoCo {mujoco.__version__}, mcap {mcap.__version__}")  # fmt: skip
    print(f"# {opts.worlds} x {opts.model} on {opts.backend}, control {opts.control_rate:g} Hz, {opts.duration:g} s per run")
    budget = 1e3 / opts.control_rate
    with tempfile.TemporaryDirectory() as where:
        path = os.path.join(where, "run.mcap")
        plain = os.path.join(where, "plain.mcap")
        sizes = {}
        if opts.warmup:  # a first fleet compiles and captures (warp: a minute): not one of the timed runs
            run(argparse.Namespace(**{**vars(opts), "duration": 1.0}), None)
        runs = [("without recording", None, True), ("recording, no inputs", plain, False), ("recording", path, True)]
        for label, record, inputs in runs * opts.repeat:
            for old in (record,) if record and os.path.exists(record) else ():
                os.remove(old)
            r = run(opts, record, inputs)
            if record:
                sizes[label] = os.path.getsize(record) / (opts.worlds * r["sim_time"])
            print(
                f"{label:18s} rtf {r['rtf']:.3f} | loop's own time per period: median {r['median']:.3f} ms, "
                f"p99 {r['p99']:.3f} ms, worst {r['worst']:.2f} ms (budget {budget:g} ms, {r['over']} over) | "
                f"{r['periods']} periods"
            )
        topics = count(path)
        size = os.path.getsize(path)
        periods = r["periods"]
        print(f"file: {size / 1e6:.2f} MB, {sum(topics.values())} messages, ring drops {r['dropped']}, "
              f"{size / (opts.worlds * r['sim_time']) / 1e3:.1f} kB per world-second")  # fmt: skip
        extra = sizes["recording"] - sizes["recording, no inputs"]
        print(f"the physics inputs (batchsim resim) add {extra / 1e3:.2f} kB per world-second to the file "
              f"({sizes['recording, no inputs'] / 1e3:.1f} -> {sizes['recording'] / 1e3:.1f})")  # fmt: skip
        for topic, n in sorted(topics.items()):
            if topic == "/diagnostics":  # every world once a sim second, and the worlds whose status changed
                print(f"  {topic:32s} {n:8d} (once a sim second: {r['sim_time']:.0f} s, and at each change of status)")
                continue
            per = opts.worlds if not topic.startswith("/") else 1
            expected = periods * per if topic not in ("/tf_static", "robot_description", "/batchsim/starts") else per
            print(f"  {topic:32s} {n:8d} of {expected:8d} expected {'ok' if n == expected else 'MISSING'}")


if __name__ == "__main__":
    main()
