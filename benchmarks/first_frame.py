"""How long after a client subscribes to a camera's image_raw its first frame arrives (issue 47).

    .venv/bin/python benchmarks/first_frame.py --runs 5

Per run: `batchsim --model rover --worlds 2 --camera-resolution 64x48` (camera rate 5 Hz: one
frame per 0.2 s), started and left 4 s; a client node, created and spun first so that its own
discovery of the fleet is done, then subscribes to `/world_1/front_camera/image_raw`. Printed:
when its subscription matched batchsim's publisher (on request: created once batchsim's graph
scan sees the subscriber) and when the first frame came, both from the subscription's creation.
Variants: the default (topics on request) and --all-topics (the publisher exists from the start).
Each run on a ROS domain of its own: a run's fleet saw the last run's client in the graph (its
endpoints linger there a while), made the topic for it and rendered before anyone asked.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fleet import Batchsim, _versions, client_node  # noqa: E402


def one_run(domain: int, extra: list[str]) -> tuple[float, float]:
    """(matched after s, first frame after s) of one run; NaN where it did not come in 20 s."""
    import rclpy
    from rclpy.event_handler import SubscriptionEventCallbacks
    from sensor_msgs.msg import Image

    fleet = Batchsim(["--model", "rover", "--worlds", "2", "--camera-resolution", "64x48", *extra], domain)
    context = None
    try:
        fleet.wait_started(120)
        context, node, executor = client_node(domain, "first_frame_probe")
        until = time.monotonic() + 4.0  # the probe's own discovery of the fleet, done before it subscribes
        while time.monotonic() < until:
            executor.spin_once(timeout_sec=0.01)
        got: list[float] = []
        matched: list[float] = []
        events = SubscriptionEventCallbacks(matched=lambda info: matched.append(time.monotonic()))
        t0 = time.monotonic()
        node.create_subscription(Image, "/world_1/front_camera/image_raw", lambda m: got.append(time.monotonic()), 10,
                                 event_callbacks=events)  # fmt: skip
        while not got and time.monotonic() - t0 < 20:
            executor.spin_once(timeout_sec=0.005)
        nan = float("nan")
        return (matched[0] - t0 if matched else nan), (got[0] - t0 if got else nan)
    finally:
        if context is not None:
            rclpy.try_shutdown(context=context)
        fleet.stop()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--domain", type=int, default=80, help="the first run's ROS domain (each run takes the next)")
    opts = p.parse_args()
    print(f"# {platform.node() or 'host'}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}; {_versions()}; "
          f"{time.strftime('%Y-%m-%d')}; camera 5 Hz (0.2 s a frame)")  # fmt: skip
    print("| topics | runs | matched after s (median, worst) | first frame after s (median, worst) |")
    print("| --- | --- | --- | --- |")
    domains = iter(range(opts.domain, opts.domain + 2 * opts.runs))  # a domain a run: no endpoint of the last one
    for label, extra in (("on request (default)", []), ("--all-topics", ["--all-topics"])):
        runs = [one_run(next(domains), extra) for _ in range(opts.runs)]
        m = [r[0] for r in runs]
        f = [r[1] for r in runs]
        print(f"| {label} | {len(runs)} | {statistics.median(m):.2f}, {max(m):.2f} | {statistics.median(f):.2f}, {max(f):.2f} |",
              flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
