"""The shards of a fleet over several devices (batchsim/backends/sharded/system.py): one backend
system per device, in this process on a thread, or in a process of its own.

Both kinds serve the same operations (`serve`): `write` takes the shard's rows of the
fleet's command array, `read` puts the shard's readings into the fleet's rows, `step`,
`reset` and the lifecycle run on the shard's system. The fleet's arrays live in one
`batchsim.memory.Memory`: local memory when the shards are threads, a shared-memory
segment when they are processes, so that a process shard reads its commands and writes
its readings where the fleet's arrays already are, and the fleet copies nothing.

    shard = ProcessShard(backend, spec, rows, device, options, memory, fleet_size)
    shard.started()                      # after starting every shard: they start at once
    shard.submit(ShardOp.STEP, 10).result()  # every shard's submit first, then every result

A process shard runs `main(FDS)` of batchsim/backends/sharded/process.py in a new Python: one request, one reply,
a control period's through a control row in the fleet's shared memory, the rest pickled on
a socket pair (batchsim/backends/sharded/messages.py). A reply carries the shard's log
records, which the fleet's process logs as its own, so a failed world's line looks the same
whatever the shard's kind. A shard process exits when the fleet's process closes the socket
or dies.
"""

from __future__ import annotations

import enum
import logging
import os
import socket
import subprocess
import sys
import time
from concurrent.futures import Future, ThreadPoolExecutor
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from batchsim.backends.sharded.messages import POLL, Bell, FleetEnd
from batchsim.backends.sharded.rows import FleetRows
from batchsim.contract import Contract
from batchsim.lifecycle import LifecycleState
from batchsim.memory import Memory
from batchsim.model import RobotSpec
from batchsim.types import Frames


class ShardOp(enum.Enum):
    """An operation the fleet asks of a shard (`serve`), pickled as it is to a shard process."""

    WRITE = "write"
    STEP = "step"
    READ = "read"
    RESET = "reset"
    CONFIGURE = "configure"
    INITIALIZE = "initialize"
    ACTIVATE = "activate"
    DEACTIVATE = "deactivate"
    CLEANUP = "cleanup"
    SHUTDOWN = "shutdown"
    ERROR = "error"
    SET_SENSOR_CONFIG = "set_sensor_config"
    PERFORM_COMMAND_MODE_SWITCH = "perform_command_mode_switch"
    RENDER = "render"
    SCAN = "scan"
    BODY_POSES = "body_poses"
    QSTATE = "qstate"
    SET_QSTATE = "set_qstate"
    POSES = "poses"  # every world's body poses into the fleet's rows (tf's each period)
    READ_POSES = "read_poses"  # read, then the poses: tf's each period, without a round trip of its own
    SET_VARIATION = "set_variation"
    WORLD_PARAMS = "world_params"
    DRAW_NUMBERS = "draw_numbers"
    RESEED = "reseed"
    # a shard process's device arrays cannot leave it: it answers these with host copies
    DEVICE_ARRAYS = "device_arrays"
    DEVICE_FRAMES = "device_frames"
    DEVICE_RANGES = "device_ranges"


# the operations a shard runs as its system's method of the member's value, as they come: the
# rest of the lifecycle, the sensors and the body poses (an answer of host arrays, as a render's)
CALLS = frozenset(ShardOp) - {
    ShardOp.WRITE, ShardOp.STEP, ShardOp.READ, ShardOp.POSES, ShardOp.READ_POSES, ShardOp.RESET, ShardOp.CONFIGURE,
    ShardOp.DEVICE_ARRAYS, ShardOp.DEVICE_FRAMES, ShardOp.DEVICE_RANGES,
}  # fmt: skip
START_TIMEOUT = 300.0  # s: a shard process importing its backend and building its model
# through the control row, unpickled
PERIOD_OPS = (ShardOp.WRITE, ShardOp.STEP, ShardOp.READ, ShardOp.POSES, ShardOp.READ_POSES)
# the shard process's program (batchsim/backends/sharded/process.py), its fds as arguments
PROCESS_MAIN = "import sys; from batchsim.backends.sharded.process import main; sys.exit(main(sys.argv[1:]))"
# s: how long a waiting side (the fleet for a reply, a shard for its next request) polls
# before it sleeps. A sleeping process wakes tens to hundreds of microseconds after its
# message arrives (more in a virtual machine, whose idle cores halt); with four such wake-ups
# per period, polling gave 2 and 4 H200s 6 % and 3 % more steps/s (benchmarks/RESULTS.md, GPU
# session 4). It keeps a core busy while it waits, so it is done only where there are cores
# to spare (spin_budget).
SPIN = 0.05


def spin_budget(nshard: int) -> float:
    """How long the fleet and each of its `nshard` shard processes poll before sleeping:
    SPIN where this process may use at least two cores per polling process, else 0."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return SPIN if cores >= 2 * (nshard + 1) else 0.0


def serve(system: Contract, rows: FleetRows, op: ShardOp, args: tuple, kwargs: dict) -> Any:
    """Run one operation of a shard on its system, moving what it needs through `rows`."""
    if op is ShardOp.WRITE:
        rows.take_command(system)
        system.write(*args)
        rows.give_status(system)
    elif op is ShardOp.STEP:
        system.step(*args)
        rows.give_status(system)
    elif op is ShardOp.READ:
        system.read(*args)
        rows.give_readings(system)
    elif op is ShardOp.POSES:
        rows.give_poses(system)
    elif op is ShardOp.READ_POSES:
        system.read(*args)
        rows.give_readings(system)
        rows.give_poses(system)
    elif op is ShardOp.RESET:
        system.reset(*args)
        rows.give_readings(system)
        rows.give_command(system)  # the reset worlds' commands are their initial ones again
    elif op is ShardOp.CONFIGURE:  # which resets every world
        value = system.configure()
        rows.give_readings(system)
        rows.give_command(system)
        return value
    elif op in CALLS:
        return getattr(system, op.value)(*args, **kwargs)
    elif op is ShardOp.DEVICE_ARRAYS:
        return {field: _host(array) for field, array in system.device_arrays().items()}
    elif op is ShardOp.DEVICE_FRAMES:
        frames = system.render(*args, device=True)
        return Frames(_host(frames.rgb), _host(frames.depth))
    elif op is ShardOp.DEVICE_RANGES:
        return _host(system.scan(*args, device=True))
    else:
        raise ValueError(f"a shard serves no operation {op!r}")
    return None


def _host(array: Any) -> np.ndarray:
    """A Warp, JAX or NumPy array as a NumPy array on the host."""
    return array.numpy() if hasattr(array, "numpy") else np.asarray(array)


class LocalShard:
    """A shard in this process: its system, run on a thread of the fleet's pool.

    Attributes:
      system: the shard's backend system (device arrays, rendering on the device).
    """

    def __init__(self, system: Contract, rows: FleetRows, pool: ThreadPoolExecutor):
        self.system = system
        self.rows = rows
        self._pool = pool

    @property
    def lifecycle_state(self) -> LifecycleState:
        return self.system.lifecycle_state

    @property
    def options(self) -> dict[str, Any]:
        return self.system.options

    def submit(self, op: ShardOp, *args: Any, **kwargs: Any) -> Future:
        return self._pool.submit(serve, self.system, self.rows, op, args, kwargs)

    def call(self, op: ShardOp, *args: Any, **kwargs: Any) -> Any:
        """Run `op` on this thread (lifecycle transitions: one shard at a time)."""
        return serve(self.system, self.rows, op, args, kwargs)

    def close(self) -> None:
        pass


class ShardProcessError(RuntimeError):
    """A shard process exited, or failed to start."""


class _Reply:
    """The answer to one request of a ProcessShard, read when asked for."""

    def __init__(self, shard: ProcessShard):
        self._shard = shard

    def result(self) -> Any:
        return self._shard._receive()  # noqa: SLF001 (its own class's reply)


class ProcessShard:
    """A shard in a process of its own, on one device; the fleet's arrays in shared memory.

    Args:
      build: the function that builds the shard's system, as "module:name" (the fleet's `build`,
        imported by name in the shard process: `batchsim:build`).
      backend: the backend's name ("warp", "mjx").
      spec: the robot (pickled to the shard process).
      rows: the fleet's worlds this shard runs.
      device: the shard's device, as the backend names it ("cuda:1", "gpu:0", "cpu").
      options: the backend's options.
      memory: the fleet's arrays, in a shared-memory segment (Memory.create(shared=True)).
      fleet_size: the fleet's world count, for log lines.
      spin: seconds the fleet and the shard process poll for a message before sleeping
        (spin_budget).
      cpus: the cores the shard process runs on (None: this process's).
      slot: the shard's control row in `memory` (its index in the fleet).

    Attributes:
      busy: seconds the shard process spent on the last request, its own work without the
        messages (benchmarks/devices.py sets it beside the fleet's wait).
      sent, began, seen: time.perf_counter() of the last request's sending (this process),
        of its beginning in the shard process (its clock: the same on Linux; 0.0 where not
        said) and of its answer's arrival here: where a period's messages take their time.
    """

    def __init__(
        self,
        build: str,
        backend: str,
        spec: RobotSpec,
        rows: range,
        device: Any,
        options: dict[str, Any],
        memory: Memory,
        fleet_size: int,
        spin: float = 0.0,
        cpus: set[int] | None = None,
        slot: int = 0,
    ):
        if memory.name is None:
            raise ValueError("a shard process needs the fleet's arrays in shared memory")
        if not isinstance(device, str):
            raise ValueError(f"a shard process names its device as a string (e.g. 'cuda:1'), got {device!r}")
        self.device = device
        self.rows = rows
        self.lifecycle_state = LifecycleState.UNKNOWN
        self.options: dict[str, Any] = {}
        self.spin = float(spin)
        self.busy = self.sent = self.began = self.seen = 0.0
        ours, theirs = socket.socketpair()
        to_shard, to_fleet = Bell.pair(), Bell.pair()
        env, local_device = device_env(device)
        root = str(Path(__file__).resolve().parents[3])
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        theirs_fds = (theirs.fileno(), to_shard.read_fd, to_fleet.write_fd)
        try:
            self._popen = subprocess.Popen(
                [sys.executable, "-c", PROCESS_MAIN, *map(str, theirs_fds)],
                pass_fds=theirs_fds,
                env=env,
                stdin=subprocess.DEVNULL,
                start_new_session=True,  # Ctrl-C goes to the fleet's process, which stops its shards
            )
        finally:
            theirs.close()
            for fd in theirs_fds[1:]:
                os.close(fd)
        self._conn = Connection(ours.detach())
        inbox, outbox = Bell(to_fleet.read_fd, -1), Bell(-1, to_shard.write_fd)
        self._end = FleetEnd(memory["control"][slot], self._conn, inbox, outbox, PERIOD_OPS, self.spin)
        self._pending = False
        from batchsim.parts.failures import mujoco_log

        start = {
            "build": build,
            "backend": backend,
            "spec": spec,
            "rows": (rows.start, rows.stop),
            "fleet_size": fleet_size,
            "device": local_device,
            "options": options,
            "layout": memory.layout,
            "memory": memory.name,
            "log_dir": None if mujoco_log() is None else str(mujoco_log().parent),
            "spin": self.spin,
            "cpus": None if cpus is None else sorted(cpus),
            "slot": slot,
        }
        try:
            self._conn.send(start)
        except OSError:
            raise self._exited() from None
        self._pending = True

    def started(self) -> None:
        """Wait until the shard process has built its system (call once, after __init__)."""
        waited = 0.0
        try:
            while not self._conn.poll(POLL):  # its start is answered on the socket
                waited += POLL
                if self._popen.poll() is not None:
                    raise self._exited()
                if waited >= START_TIMEOUT:
                    raise ShardProcessError(f"the shard process of {self.device} did not start in {START_TIMEOUT:g} s")
            reply = self._answer(*self._conn.recv())
        except (OSError, EOFError):
            raise self._exited() from None
        finally:
            self._pending = False
        self.options = dict(reply["options"], device=self.device)

    def __repr__(self) -> str:
        return f"ProcessShard({self.device}, worlds {self.rows.start}..{self.rows.stop - 1}, pid {self._popen.pid})"

    @property
    def pid(self) -> int:
        return self._popen.pid

    def submit(self, op: ShardOp, *args: Any, **kwargs: Any) -> _Reply:
        """Send one request; its `result()` waits for the reply (one request at a time)."""
        if self._pending:
            raise RuntimeError(f"{self!r}: a request is already waiting for its reply")
        self.sent = time.perf_counter()
        try:
            self._end.send(op, args, kwargs)
        except (OSError, EOFError):
            raise self._exited() from None
        self._pending = True
        return _Reply(self)

    def call(self, op: ShardOp, *args: Any, **kwargs: Any) -> Any:
        return self.submit(op, *args, **kwargs).result()

    def _receive(self) -> Any:
        try:
            while not self._end.answered(POLL):
                if self._end.peer_closed() or self._popen.poll() is not None:
                    raise self._exited()
            self.seen, self.began = time.perf_counter(), self._end.began()
            return self._answer(*self._end.reply())
        except (OSError, EOFError):
            raise self._exited() from None
        finally:
            self._pending = False

    def _answer(self, ok: bool, value: Any, lifecycle: int | None, records: list, busy: float) -> Any:
        self.busy = busy
        for name, level, message in records:  # the shard's log lines, as if logged here
            logging.getLogger(name).log(level, "%s", message)
        if lifecycle is not None:
            self.lifecycle_state = LifecycleState(lifecycle)
        if not ok:
            raise value
        return value

    def _exited(self) -> ShardProcessError:
        try:
            code = self._popen.wait(5.0)
        except subprocess.TimeoutExpired:
            code = None
        self.lifecycle_state = LifecycleState.FINALIZED  # nothing more to ask of it
        return ShardProcessError(
            f"the shard process of {self.device} (worlds {self.rows.start}..{self.rows.stop - 1}, pid "
            f"{self._popen.pid}) " + ("stopped answering" if code is None else f"exited with code {code}")
        )

    def close(self, timeout: float = 10.0) -> None:
        """Stop the shard process (it shuts its system down as it exits). Idempotent."""
        if self._conn.closed:
            return
        self._conn.close()  # the shard process sees the end of its socket and exits
        self._end.close()
        try:
            self._popen.wait(timeout)
        except subprocess.TimeoutExpired:
            self._popen.kill()
            self._popen.wait()


def device_env(device: str) -> tuple[dict[str, str], str]:
    """The shard process's environment and its name for `device`: a GPU shard sees only its
    own GPU (CUDA_VISIBLE_DEVICES), so that it neither opens a context on the others nor,
    with JAX, takes memory there; it then calls it device 0."""
    env = dict(os.environ)
    platform, _, index = device.partition(":")
    if platform not in ("cuda", "gpu"):
        return env, device
    visible = [v for v in env.get("CUDA_VISIBLE_DEVICES", "").split(",") if v.strip()]
    k = int(index or 0)
    env["CUDA_VISIBLE_DEVICES"] = visible[k] if k < len(visible) else str(k)
    return env, f"{platform}:0"
