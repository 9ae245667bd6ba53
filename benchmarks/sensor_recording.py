"""Recording cameras: does the recorder keep up, and does every frame reach the file?

    .venv/bin/python benchmarks/sensor_recording.py                 # 16 rovers, 64x64 RGB-D at 30 Hz
    .venv/bin/python benchmarks/sensor_recording.py --worlds 64 --rtf 0 --duration 5

The loop runs in this process as `batchsim --model rover --controllers none` runs it (the ROS 2
bridge with its worker in a process, no subscriber), recording every world's camera
(`front_camera/image_raw`, `front_camera/depth/image_raw`, `front_camera/camera_info`) and
nothing else, at each `--rtf` given: the RTF held, the loop's own time per period, the
frames in the file against the frames the sampler rendered, the samples the recorder missed
(its closing line), and the frames a second and megabytes a second it wrote. Then the
recorder's own part alone (ros_bridge/worker/sensor_recording.py's `take`: reading the
blocks, framing, the file's records and zstd chunks, into memory) on synthetic frames: how
many frames a second one recorder can write. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import io
import os
import platform
import sys
import tempfile
import time
import types
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # its siblings

from paced_fleet import timed_run  # noqa: E402
from recording import count  # noqa: E402  (the file's messages per topic, as recording.py counts them)

TOPICS = ("front_camera/image_raw", "front_camera/depth/image_raw", "front_camera/camera_info")


def _sensors(opts: argparse.Namespace) -> dict:
    size = {"width": opts.size, "height": opts.size}
    return {"sensors": {"camera_rate": opts.camera_rate, "cameras": {"front_camera": size}}}


def run(opts: argparse.Namespace, rtf: float, path: str) -> dict:
    import batchsim
    from batchsim.loop import SimLoop
    from ros_bridge.bridge import BridgeOptions, start_bridge
    from ros_bridge.options import RecordOptions
    from ros_bridge.sensor_topics import SensorFeed

    sim = batchsim.make("rover", opts.worlds, "cpu", sensors=_sensors(opts))
    sim.configure()
    sim.activate()
    loop = SimLoop(sim, control_rate=opts.control_rate, rtf=rtf, duration=opts.duration)
    host = start_bridge(sim, loop, BridgeOptions(record=RecordOptions(path, topics=TOPICS)))
    try:
        figures = timed_run(loop)
        feed = next(p for p in loop.participants if isinstance(p, SensorFeed))
        figures["rendered"] = feed.sampler.produced["front_camera"]
    finally:
        host.close()  # the recorder finishes its file
        sim.shutdown()
    figures["wall"] = loop.sim_time / figures["rtf"]
    return figures


def recorder_alone(opts: argparse.Namespace, periods: int = 600) -> tuple[float, float]:
    """Frames a second and MB a second `SensorRecording.take` writes, a period's share of the
    worlds (spread over the camera period, as the cpu backend renders) per call."""
    import batchsim
    from ros_bridge.protocol.sensor_blocks import WANT_DEPTH, WANT_INFO, WANT_RGB, SensorBlock
    from ros_bridge.recording import RecordSpec
    from ros_bridge.sensor_topics import sensor_plan
    from ros_bridge.worker.mcap_file import BlockWriter
    from ros_bridge.worker.sensor_recording import SensorRecording

    n = opts.worlds
    sensors = sensor_plan(batchsim.make("rover", 1, "cpu", sensors=_sensors(opts)))
    bits = (WANT_RGB | WANT_DEPTH | WANT_INFO,) + (0,) * len(sensors.lidars)
    spec = RecordSpec((), False, False, False, False, tuple(range(n)), (), (), sensors=bits)
    memory = {name: np.zeros(shape, dtype) for name, shape, dtype in [*sensors.arrays(n), *spec.arrays(1)]}
    plan = types.SimpleNamespace(recording=spec, sensors=sensors, namespaces=[f"world_{w}" for w in range(n)])
    stream = io.BytesIO()
    writer = BlockWriter(stream, compression="zstd")
    writer.start(profile="ros2", library="benchmark")
    schema = writer.register_schema(name="sensor_msgs/msg/Image", encoding="ros2msg", data=b"")
    recording = SensorRecording(
        plan, memory, lambda t, m: writer.register_channel(t, "cdr", schema, {}), writer
    )
    block = SensorBlock(memory, "cam0", ("rgb", "depth"))
    rng = np.random.default_rng(0)
    s = opts.size
    rgb = rng.integers(0, 255, (n, s, s, 3), dtype=np.uint8)
    depth = rng.random((n, s, s), dtype=np.float32)
    phases = max(1, round(opts.control_rate / opts.camera_rate))
    frames = 0
    t = time.perf_counter()
    for k in range(periods):
        worlds = np.arange(k % phases, n, phases)
        block.write(worlds, k / opts.control_rate, {"rgb": (worlds, rgb[worlds]), "depth": (worlds, depth[worlds])})
        recording.take()
        frames += len(worlds)
    writer.finish()
    wall = time.perf_counter() - t
    return frames / wall, stream.tell() / wall / 1e6


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--worlds", type=int, default=16)
    p.add_argument("--size", type=int, default=64, help="the camera's width and height")
    p.add_argument("--camera-rate", type=float, default=30.0)
    p.add_argument("--control-rate", type=float, default=100.0)
    p.add_argument("--duration", type=float, default=20.0, help="sim seconds per run")
    p.add_argument("--rtf", type=float, action="append", help="runs at these RTFs (default: 1, then 0)")
    p.add_argument("--domain", type=int, default=91)
    opts = p.parse_args()
    os.environ.update({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": str(opts.domain)})
    import mcap
    import mujoco

    print(f"# {platform.node()}: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
          f"Python {platform.python_version()}, MuJoCo {mujoco.__version__}, mcap {mcap.__version__}; "
          f"load average {os.getloadavg()[0]:.2f}")  # fmt: skip
    print(f"# {opts.worlds} rovers on cpu, a {opts.size}x{opts.size} RGB-D camera at {opts.camera_rate:g} Hz, "
          f"control {opts.control_rate:g} Hz, {opts.duration:g} s per run; recorded: {', '.join(TOPICS)}")  # fmt: skip
    with tempfile.TemporaryDirectory() as where:
        for rtf in opts.rtf or [1.0, 0.0]:
            path = os.path.join(where, f"rtf{rtf:g}.mcap")
            r = run(opts, rtf, path)
            topics = count(path)
            frames = topics["front_camera/image_raw"]
            complete = all(n == frames for n in topics.values())
            print(
                f"rtf {rtf:g}: held {r['rtf']:.3f} | loop's own time per period: median {r['median']:.2f} ms, "
                f"p99 {r['p99']:.2f} ms | frames in the file {frames} of {r['rendered']} rendered "
                f"({'depth and camera_info alike' if complete else dict(topics)}) | "
                f"{frames / r['wall']:.0f} frames/s, {os.path.getsize(path) / r['wall'] / 1e6:.1f} MB/s written"
            )
    fps, mbps = recorder_alone(opts)
    print(f"the recorder's take() alone: {fps:.0f} frames/s (RGB-D + camera_info), {mbps:.0f} MB/s of file")


if __name__ == "__main__":
    main()
