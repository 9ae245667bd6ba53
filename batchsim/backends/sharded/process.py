"""The shard process of a fleet over several devices (batchsim/backends/sharded/shards.py starts
it with PROCESS_MAIN): one system of its device's worlds, built by the fleet's `build` (named as
"module:name": the contract sits above the backends, so it is imported by name), serving one
request at a time until the fleet closes its socket or dies.
"""

from __future__ import annotations

import importlib
import logging
import os
import time
from multiprocessing.connection import Connection

from batchsim.backends.sharded.messages import POLL, Bell, Records, ShardEnd, picklable
from batchsim.backends.sharded.rows import FleetRows
from batchsim.backends.sharded.shards import PERIOD_OPS, serve
from batchsim.contract import Contract
from batchsim.lifecycle import LifecycleState
from batchsim.memory import Memory
from batchsim.parts.failures import set_log_dir


def main(argv: list[str]) -> int:
    """The shard process: argv is its socket's, its inbox bell's and its outbox bell's fds."""
    conn = Connection(int(argv[0]))
    inbox, outbox = Bell(int(argv[1]), -1), Bell(-1, int(argv[2]))
    records = Records()
    root = logging.getLogger()
    root.addHandler(records)
    root.setLevel(logging.INFO)
    system: Contract | None = None
    memory: Memory | None = None
    try:
        start = conn.recv()
        try:
            from batchsim.backends import Backend, backend_class

            if start["log_dir"] is not None:
                set_log_dir(start["log_dir"])
            if start.get("cpus"):
                os.sched_setaffinity(0, start["cpus"])
            memory = Memory.attach(start["layout"], start["memory"])
            cls = backend_class(Backend.parse(start["backend"]))
            module, _, name = start["build"].partition(":")
            build = getattr(importlib.import_module(module), name)  # above this package: by name
            rows = range(*start["rows"])
            system = build(start["spec"], len(rows), cls, **{**start["options"], "device": start["device"]})
            system.number_worlds_as(rows.start, start["fleet_size"])
            fleet_rows = FleetRows(memory, rows)
            fleet_rows.share(system)
            conn.send((True, {"options": system.options}, int(system.lifecycle_state), records.take(), 0.0))
        except Exception as e:
            conn.send((False, picklable(e), None, records.take(), 0.0))
            return 1
        end = ShardEnd(memory["control"][start["slot"]], conn, inbox, outbox, PERIOD_OPS, start["spin"])
        while True:
            try:
                request = end.next(POLL)
            except EOFError:
                return 0
            if request is None:
                continue
            op, args, kwargs = request
            begin = time.perf_counter()
            try:
                value = serve(system, fleet_rows, op, args, kwargs)
                end.answer(True, value, int(system.lifecycle_state), records.take(), time.perf_counter() - begin, begin)
            except Exception as e:
                end.answer(False, e, int(system.lifecycle_state), records.take(), 0.0)
    except (EOFError, BrokenPipeError, ConnectionResetError, KeyboardInterrupt):
        return 0
    finally:
        if system is not None and system.lifecycle_state not in (
            LifecycleState.UNKNOWN,
            LifecycleState.FINALIZED,
        ):
            try:
                system.shutdown()
            except Exception:
                pass
        if memory is not None:
            memory.close()
