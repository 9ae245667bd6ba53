"""How many messages a second the recorder writes into its MCAP file, against mcap's own writer.

    .venv/bin/python benchmarks/recorder_speed.py --worlds 1024 --periods 200

The recorder process's write path (ros_bridge/worker/recorder.py's `McapRecording.write`: the
CDR rows filled from a period's values, the Message records, indexes and zstd chunks laid out
a block at a time by `BlockWriter`) is timed on periods as the loop's ring hands them over
(the arm's default topics: joint_states, the wrist wrench, /tf, /clock, every world), beside
the raw library doing only its own part for the same messages: mcap's `Writer.add_message`
per message, the payloads already serialized, into the same kind of file. Both write into
memory, not a disk. Rounds alternate; the best and the median of each side are printed, and
the rate one recorder needs for the fleet at --control-rate. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import io
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def periods(plan, n: int, seed: int = 0):
    from ros_bridge.protocol.recording import RecordedPeriod

    rng = np.random.default_rng(seed)
    spec = plan.recording
    nrow = len(spec.worlds)
    out = []
    for k in range(n):
        meta = np.array([k, k, 0.01 * (k + 1), 0.0])
        channels = {
            c: rng.standard_normal((nrow, w)) for c, w in zip(spec.channels, spec.widths, strict=True)
        }
        out.append(RecordedPeriod(meta, np.zeros(nrow, np.uint8), channels))
    return out


def project(plan, work) -> tuple[float, int]:
    from ros_bridge.worker.recorder import McapRecording

    stream = io.BytesIO()
    recording = McapRecording(plan, stream)
    recording.write(work[0])  # the first period also writes the latched messages, once: not timed
    first = recording.messages
    t0 = time.perf_counter()
    for period in work[1:]:
        recording.write(period)
    recording.finish()
    return time.perf_counter() - t0, recording.messages - first


def raw(payloads: list[tuple[int, int, bytes]]) -> float:
    """mcap's Writer alone: one add_message per message, the bytes ready."""
    from mcap.writer import CompressionType, Writer

    writer = Writer(io.BytesIO(), chunk_size=1 << 20, compression=CompressionType.ZSTD)
    writer.start(profile="ros2", library="raw")
    schema = writer.register_schema(name="x", encoding="ros2msg", data=b"")
    channels = {
        c: writer.register_channel(topic=f"/{c}", message_encoding="cdr", schema_id=schema)
        for c, _, _ in payloads[:5000]
    }
    sequence: dict[int, int] = {}
    t0 = time.perf_counter()
    for c, t, data in payloads:
        ch = channels.get(c, 1)
        seq = sequence.get(ch, 0)
        sequence[ch] = seq + 1
        writer.add_message(ch, log_time=t, data=data, publish_time=t, sequence=seq)
    writer.finish()
    return time.perf_counter() - t0


def messages_of(plan, work) -> list[tuple[int, int, bytes]]:
    """The messages the project path writes, as (channel, time, bytes), for the raw writer."""
    from mcap.reader import make_reader

    from ros_bridge.worker.recorder import McapRecording

    stream = io.BytesIO()
    recording = McapRecording(plan, stream)
    recording.write(work[0])
    latched = recording.messages
    for period in work[1:]:
        recording.write(period)
    recording.finish()
    stream.seek(0)
    return [
        (m.channel_id, m.log_time, m.data)
        for _, _, m in make_reader(stream).iter_messages(log_time_order=False)
    ][latched:]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--worlds", type=int, default=1024)
    p.add_argument("--model", default="arm")
    p.add_argument("--periods", type=int, default=200)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--control-rate", type=float, default=100.0)
    opts = p.parse_args()

    import mcap
    import mujoco

    import batchsim
    from batchsim.controllers import default_controllers, load_controllers
    from ros_bridge.bridge import BridgeOptions
    from ros_bridge.options import RecordOptions
    from ros_bridge.plan import build_plan

    sim = batchsim.make(opts.model, opts.worlds, "cpu")
    sim.configure()
    manager = load_controllers(default_controllers(opts.model), sim.spec, opts.worlds)
    plan = build_plan(sim, opts.control_rate, BridgeOptions(record=RecordOptions("unused.mcap")), manager, 1)[
        0
    ]
    work = periods(plan, opts.periods)
    payloads = messages_of(plan, work)
    n = len(payloads)
    print(
        f"# {platform.node() or 'vm'} | {platform.machine()} | python {platform.python_version()} | "
        f"mujoco {mujoco.__version__} | mcap {mcap.__version__} | {time.strftime('%Y-%m-%d')}"
    )
    print(
        f"# {opts.worlds} x {opts.model}, {opts.periods} periods, {n} messages ({n // (opts.periods - 1)} a period; the first period, with the latched messages, not counted)"
    )
    ours, theirs = [], []
    for _ in range(opts.rounds):
        seconds, count = project(plan, work)
        assert count == n
        ours.append(n / seconds)
        theirs.append(n / raw(payloads))
    need = n / (opts.periods - 1) * opts.control_rate
    print(
        f"recorder (McapRecording.write)  best {max(ours):>12,.0f}  median {statistics.median(ours):>12,.0f} messages/s"
    )
    print(
        f"mcap Writer.add_message alone   best {max(theirs):>12,.0f}  median {statistics.median(theirs):>12,.0f} messages/s"
    )
    print(f"ratio recorder / raw (medians)  {statistics.median(ours) / statistics.median(theirs):.2f}")
    print(
        f"the fleet at {opts.control_rate:g} Hz needs {need:,.0f} messages/s: the recorder takes {statistics.median(ours) / need:.1f}x that"
    )


if __name__ == "__main__":
    main()
