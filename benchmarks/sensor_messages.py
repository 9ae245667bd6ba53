"""Building sensor messages for the bridge: CDR bytes in bulk against filling message objects.

Per message kind and size, the two ways a worker can turn a sample row into what
`Publisher.publish` takes, timed per message (median of rounds, interleaved):

  bulk     ros_bridge.sensor_messages.Framing.payload: the row's serialized prefix with the
           stamp patched, the payload and the suffix joined (one copy); `publish(bytes)`
           hands these to the middleware as they are
  message  a preallocated message per world: stamp set, payload assigned (`msg.data =
           row.tobytes()`, `msg.ranges = array('f', ...)`), then rclpy's conversion and
           serialization (`serialize_message`, what `publish(msg)` does before the middleware)

    .venv/bin/python benchmarks/sensor_messages.py
"""

from __future__ import annotations

import array
import datetime
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from rclpy.serialization import serialize_message  # noqa: E402
from sensor_msgs.msg import Image, LaserScan  # noqa: E402

import batchsim  # noqa: E402
from ros_bridge.worker.sensor_messages import image_framing, laser_scan_framing  # noqa: E402


def per_second(body: Callable[[], None], seconds: float = 0.6, rounds: int = 5) -> float:
    body()
    t = time.perf_counter()
    body()
    calls = max(1, round(seconds / rounds / max(time.perf_counter() - t, 1e-7)))
    rates = []
    for _ in range(rounds):
        t = time.perf_counter()
        for _ in range(calls):
            body()
        rates.append(calls / (time.perf_counter() - t))
    return float(np.median(rates))


def main() -> int:
    frames = ["world_0/front_camera"]
    print(f"# {platform.node() or 'host'}, Python {platform.python_version()}, numpy {np.__version__}, {datetime.date.today()}")
    print("| message | payload bytes | bulk msgs/s | message objects msgs/s | ratio |")
    print("| --- | --- | --- | --- | --- |")
    for w, h in ((64, 64), (320, 240)):
        sim = batchsim.make("rover", 1, "cpu", sensors={"sensors": {"camera_resolution": [w, h]}})
        cam = sim.sensors.camera("front_camera")
        for depth in (False, True):
            row = np.zeros((h, w), np.float32) if depth else np.zeros((h, w, 3), np.uint8)
            framing = image_framing(cam, frames, depth, "t")
            msg = Image(height=h, width=w, encoding="32FC1" if depth else "rgb8", step=w * (4 if depth else 3))
            msg.header.frame_id = frames[0]

            def as_message(msg=msg, row=row) -> None:
                msg.header.stamp.sec, msg.header.stamp.nanosec = 1, 2
                msg.data = row.tobytes()
                serialize_message(msg)

            bulk = per_second(lambda framing=framing, row=row: framing.payload(0, 1, 2, row))
            objects = per_second(as_message)
            print(f"| Image {'32FC1' if depth else 'rgb8'} {w}x{h} | {row.nbytes} | {bulk:,.0f} | {objects:,.0f} | {bulk / objects:.1f} |")
    lidar = sim.sensors.lidar("base_scan")
    ranges = np.linspace(1, 2, lidar.nray, dtype=np.float32)
    framing = laser_scan_framing(lidar, 10.0, frames, "t")
    msg = LaserScan(angle_min=lidar.angle_min, angle_max=lidar.angle_max, angle_increment=lidar.angle_increment)

    def scan_message() -> None:
        msg.header.stamp.sec, msg.header.stamp.nanosec = 1, 2
        msg.ranges = array.array("f", ranges.tobytes())
        serialize_message(msg)

    bulk = per_second(lambda: framing.payload(0, 1, 2, ranges))
    objects = per_second(scan_message)
    print(f"| LaserScan {lidar.nray} rays | {ranges.nbytes} | {bulk:,.0f} | {objects:,.0f} | {bulk / objects:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
