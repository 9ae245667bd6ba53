"""A bridge worker's process: `python -m ros_bridge.worker INDEX WAKE_FD STATUS_FD NOTIFY_FD [--check]`.

supervisor.py starts one per range of worlds and hands it the plan on standard input; it
reports `ready`, `conflict KIND MESSAGE` or `error ...` on STATUS_FD, then serves until
WAKE_FD reaches EOF (the physics process went) or carries `q`.
"""

from __future__ import annotations

import ctypes
import gc
import os
import pickle
import signal
import sys
from typing import Any

from batchsim.memory import Memory
from ros_bridge.plan import FleetPlan


def die_with_parent() -> None:
    """SIGTERM when the physics process dies, however it dies (Linux)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def main(argv: list[str] | None = None) -> int:
    from ros_bridge.worker.core import Worker  # rclpy: here, so that view.py takes die_with_parent without it

    argv = list(sys.argv[1:] if argv is None else argv)
    index, wake_fd, status_fd, notify_fd = (int(a) for a in argv[:4])
    check = "--check" in argv
    parent = os.getppid()
    die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the physics process, which stops us

    def on_term(signum: int, frame: Any) -> None:
        raise SystemExit(0)

    signal.signal(signal.SIGTERM, on_term)
    if os.getppid() != parent:
        return 0
    status = os.fdopen(status_fd, "w", buffering=1)
    # a worker writes nothing to stdout (its status goes to STATUS_FD, its log to stderr),
    # but rclpy's EventsExecutor prints two lines there for every timer beyond 8 on a clock,
    # and each action server created on request brings one (rcl_action's goal expiry)
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 1)
    os.close(null)
    try:
        plan: FleetPlan = pickle.load(sys.stdin.buffer)
    except (EOFError, pickle.UnpicklingError):
        return 0  # the physics process stopped (Ctrl-C) before it handed the whole plan over
    memory: Memory | None = None
    worker = None
    ready = False
    try:
        memory = Memory.attach(plan.layout, plan.memory_name)
        os.set_blocking(notify_fd, False)
        worker = Worker(plan, index, memory, notify_fd=notify_fd if plan.lockstep else None)
        conflict = worker.check_conflicts() if check else None
        if conflict is not None:
            status.write(f"conflict {conflict[0]} {conflict[1]}\n")
            return 0
        if os.environ.get("BATCHSIM_WORKER_STACKS"):  # a developer's view of where the time goes
            from ros_bridge.worker import stacks

            stacks.start(os.environ["BATCHSIM_WORKER_STACKS"], index)
        worker.build()
        worker.start()
        # what start-up made is never scanned again, as the loop does (SimLoop): a full collection
        # of a 512-world worker took 16-48 ms (2-core VM), a stall in which snapshots went unread
        gc.collect()
        gc.freeze()
        status.write("ready\n")
        ready = True
        worker.serve(wake_fd)
        return 0
    except SystemExit:
        return 0
    except BaseException as e:
        if os.getppid() != parent:
            return 0  # the physics process went (and took the shared memory): nothing to say
        if not ready:
            try:
                status.write(f"error {type(e).__name__}: {e}\n")
            except OSError:
                pass
        raise
    finally:
        if worker is not None:
            worker.close()
        if memory is not None:
            memory.close()

