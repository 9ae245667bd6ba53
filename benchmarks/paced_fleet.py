"""The fleet `batchsim` runs, paced at RTF 1 with the loop's own time per period measured:
what benchmarks/recording.py and view.py both time, each with its own bridge options."""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np


@contextmanager
def paced_fleet(opts: argparse.Namespace, bridge_options: Any) -> Iterator[tuple[Any, Any, Any]]:
    """(sim, loop, bridge host) of `opts.worlds` x `opts.model` on `opts.backend` (over
    `opts.devices`, if it has them: 'all' or '0,1', one shard process each), the model's
    default controllers, RTF 1 for `opts.duration` sim seconds at `opts.control_rate`, the loop
    thread's SCHED_FIFO where allowed; the bridge closed and the sim shut down on leaving."""
    import batchsim
    from batchsim.controllers import default_controllers, load_controllers
    from batchsim.loop import SimLoop
    from batchsim.loop.realtime import DEFAULT_THREAD_PRIORITY
    from ros_bridge.bridge import start_bridge

    options: dict[str, Any] = {}
    if getattr(opts, "devices", None):  # one process per device, as `batchsim --devices` runs them
        from batchsim.backends import backend_class

        have = backend_class(batchsim.Backend.parse(opts.backend)).available_devices()
        chosen = have if opts.devices == "all" else [have[int(d)] for d in opts.devices.split(",")]
        options.update(devices=chosen, processes=True)
    sim = batchsim.make(opts.model, opts.worlds, opts.backend, **options)
    sim.configure()
    sim.activate()
    manager = load_controllers(default_controllers(opts.model), sim.spec, opts.worlds)
    loop = SimLoop(
        sim, control_rate=opts.control_rate, rtf=1.0, duration=opts.duration, participants=[manager],
        thread_priority=DEFAULT_THREAD_PRIORITY,
    )  # fmt: skip
    host = start_bridge(sim, loop, bridge_options, manager)
    try:
        yield sim, loop, host
    finally:
        host.close()  # a recorder finishes its file
        sim.shutdown()


def timed_run(loop: Any, after: Callable[[], None] | None = None) -> dict:
    """Run `loop` to its end, timing each period's own work (the pacing sleep excluded); `after`
    runs once the loop stops, before the figures. The RTF held (sim time over wall time from the
    first period's start), and the periods' median, p99 and worst in ms, and how many ran over."""
    own: list[float] = []
    starts: list[float] = []
    run_period = loop.run_period

    def timed(nstep: int | None = None) -> None:
        t = time.perf_counter()
        run_period(nstep)
        starts.append(t)
        own.append(time.perf_counter() - t)

    loop.run_period = timed
    try:
        loop.run()
        end = time.perf_counter()  # before `after`: what it does is not the loop's time
    finally:
        if after is not None:
            after()
    wall = end - starts[0]
    ms = np.array(own) * 1e3
    return {
        "periods": len(own),
        "rtf": loop.sim_time / (wall + 1.0 / loop.control_rate),
        "median": float(np.median(ms)),
        "p99": float(np.percentile(ms, 99)),
        "worst": float(ms.max()),
        "over": int((ms > 1e3 / loop.control_rate).sum()),
        "sim_time": loop.sim_time,
    }
