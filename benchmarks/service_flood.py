"""A flood of switch_controller calls on one world against its neighbours' services (issue 47).

    .venv/bin/python benchmarks/service_flood.py --seconds 10

`batchsim --worlds 16` (the arm, its controllers, one bridge worker: every world on the same
executor thread) on a private ROS domain. One process floods world 3's
`controller_manager/switch_controller` with `--clients` calls in flight, each answered call
followed by a new one (deactivating and activating the trajectory controller in turn); meanwhile this
process calls world 0's `switch_controller` (an empty switch) every 0.2 s and times each answer.
Two windows: quiet, then flooded. Printed per window: world 0's answer times (p50, p99, worst)
and how many of the flood's calls were answered and how many refused. Nothing is asserted.
"""

from __future__ import annotations

import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fleet import Batchsim, _versions, client_node, flood_args, keep_in_flight, start_flooder  # noqa: E402

JTC = "joint_trajectory_controller"


def flood(domain: int, world: int, seconds: float, outstanding: int) -> None:
    """The flooding process: one client keeping `outstanding` calls in flight, a new one sent as
    each is answered (what a client looping over call_async does)."""
    from controller_manager_msgs.srv import SwitchController

    context, node, executor = client_node(domain, "flooder")
    client = node.create_client(SwitchController, f"/world_{world}/controller_manager/switch_controller")
    client.wait_for_service(timeout_sec=30)

    def send(k: int):
        request = SwitchController.Request(strictness=1)
        (request.deactivate_controllers if k % 2 == 0 else request.activate_controllers).append(JTC)
        return client.call_async(request)

    keep_in_flight(context, executor, send, lambda f: "ok" if f.result().ok else "refused", ("ok", "refused"), outstanding, seconds)


def main() -> None:
    opts = flood_args(__doc__, 58, "calls", flood)
    if opts is None:  # this process was the flooder
        return
    from controller_manager_msgs.srv import SwitchController

    fleet = Batchsim(["--worlds", "16", "--bridge-workers", "1", "--quiet"], opts.domain)
    try:
        fleet.wait_started(120)
        context, node, executor = client_node(opts.domain, "service_flood_probe")
        probe = node.create_client(SwitchController, "/world_0/controller_manager/switch_controller")
        assert probe.wait_for_service(timeout_sec=60)
        print(f"# {platform.node() or 'host'}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}; {_versions()}; "
              f"{time.strftime('%Y-%m-%d')}; 16 arms, 1 bridge worker, {opts.clients} flooding calls in flight on world {opts.world}")  # fmt: skip
        print("| window | world 0's answers | p50 ms | p99 ms | worst ms | flood answered | flood refused |")
        print("| --- | --- | --- | --- | --- | --- | --- |")

        def window(label: str, flooder: subprocess.Popen | None) -> None:
            times = []
            end = time.monotonic() + opts.seconds
            while time.monotonic() < end:
                t0 = time.monotonic()
                future = probe.call_async(SwitchController.Request(strictness=1))
                executor.spin_until_future_complete(future, timeout_sec=10)
                times.append(1e3 * (time.monotonic() - t0) if future.done() else float("inf"))
                time.sleep(max(0.0, 0.2 - (time.monotonic() - t0)))
            flood_ok, refused = ("-", "-")
            if flooder is not None:
                flood_ok, refused = flooder.communicate(timeout=120)[0].split()
            times.sort()
            p99 = times[min(len(times) - 1, int(0.99 * len(times)))]
            print(f"| {label} | {len(times)} | {statistics.median(times):.1f} | {p99:.1f} | {times[-1]:.1f} | {flood_ok} | {refused} |",
                  flush=True)  # fmt: skip

        window("quiet", None)
        flooder = start_flooder(__file__, opts.world, opts.domain, opts.seconds, opts.clients)
        time.sleep(2.0)  # its clients found the service
        window("flooded", flooder)
        context.try_shutdown()
    finally:
        fleet.stop()


if __name__ == "__main__":
    main()
