"""Start-up of a fleet: will it fit in memory, what is it doing, and a prompt exit on Ctrl-C.

- `fleet_memory` adds up what a world costs (the physics its backend's class states, the
  contract's host arrays, the ROS 2 bridge's endpoints) from measured constants;
  `check_host_memory` / `check_device_memory` refuse a fleet that will not fit with one line,
  before anything is allocated.
- `Progress` shows each start-up stage that takes longer than a second: a live line on a
  terminal, one line when it starts and one when it ends in a log.
- `StartupGuard` makes SIGINT/SIGTERM during start-up end the process promptly with one
  line and exit code 128 + the signal (130, 143), even inside a long library call.

No jax or warp here: device memory comes from the backend (`device_memory`, where it has one).
"""

from __future__ import annotations

import dataclasses
import os
import signal
import socket
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TextIO

import mujoco
import numpy as np

from batchsim.model import RobotSpec

# --- what a world costs, measured (2026-11-21, this 2-core machine, MuJoCo 4, RSS deltas
# between two fleet sizes of one process unless said otherwise) ---

# The ROS 2 bridge, measured 2026-11-26 (arm, default controllers, one bridge worker, PSS of
# the worker and the loop's process at 16, 256 and 1024 worlds: 101/188/479 MB and 54/55/61 MB):
# each world's endpoints and message buffers 0.36-0.38 MB in its worker plus ~8 kB in the loop's
# process, rounded up; each worker process (a Python with rclpy and Fast DDS) ~95 MB before any
# world. Re-measure it so when the bridge changes (benchmarks/RESULTS.md, "The bridge's memory").
ROS_BRIDGE_BYTES_PER_WORLD = 400_000
ROS_BRIDGE_BYTES_PER_WORKER = 100_000_000

# the contract's host arrays (readings, command, ctrl: what read() and write() fill), per world,
# in float64s of (mjSTATE_FULLPHYSICS + nq + nv + nu + nsensordata). Measured on cpu, whose
# mujoco.batch rows are those arrays: 3.2x for arm (1260 B), 3.0x for quadruped (2440 B),
# 2.6x for humanoid (2780 B), make() at 2000 vs 22000 worlds; the whole
# `batchsim --no-ros --controllers none` run takes 1470 B a world for the arm (peak RSS at
# 30000 vs 300000 worlds: 3.75x); 4x covers them.
HOST_ROW_FACTOR = 4.0
# controllers: the arm's default set (joint_state_broadcaster, joint_trajectory_controller,
# a wrist broadcaster) added 700 B a world over its 6 command interfaces (peak RSS of the
# run above with and without them): ~120 B per command interface, rounded up.
CONTROLLER_BYTES_PER_COMMAND = 160
# what each backend's physics takes beside these: its class's `physics_memory`
# (batchsim.backends.footprint holds the shipped backends' measurements)

# the process itself: 64 MB peak RSS for 16 arms without ROS, 123 MB with it (imports,
# the model, DDS); jax and warp add their runtimes: rounded up.
FIXED_HOST_BYTES = 300_000_000

# warn (not refuse) above this fraction of what is available
WARN_FRACTION = 0.8


class MemoryCheckError(ValueError):
    """A fleet that will not fit in the memory available; one line, naming the way out."""


@dataclasses.dataclass(frozen=True)
class DeviceMemory:
    """A device's memory in bytes, as its backend reports it."""

    free: int
    total: int


@dataclasses.dataclass(frozen=True)
class MemoryEstimate:
    """What `nworld` worlds of one model will take, in bytes.

    host: RAM in all (`fixed` + nworld x (host physics + `ros_per_world` + `controllers_per_world`));
    device: GPU memory (nworld x `physics_per_world`; 0 when the backend runs on the host);
    physics_per_world: the backend's per-world physics, on the device or the host.
    """

    nworld: int
    backend: str
    host: int
    device: int
    physics_per_world: int
    ros_per_world: int
    fixed: int
    controllers_per_world: int = 0
    ros_fixed: int = 0  # the bridge's worker processes, before any world (in `fixed`)

    def breakdown(self) -> str:
        parts = [f"physics {_size(self.nworld * self.physics_per_world)}"]
        if self.device:
            parts[0] += " on the device"
        if self.controllers_per_world:
            parts.append(f"controllers {_size(self.nworld * self.controllers_per_world)}")
        if self.ros_per_world:
            parts.append(f"ROS 2 bridge {_size(self.nworld * self.ros_per_world + self.ros_fixed)}")
        return ", ".join(parts)


@dataclasses.dataclass(frozen=True)
class PhysicsMemory:
    """What a backend's physics takes beside the contract's host arrays, in bytes, as its class
    states it (`physics_memory`, batchsim.backends):

    per_world: each world's engine state, on the backend's device or, where it runs on the
      host, in RAM (0 where the engine's rows are the host arrays themselves: cpu's batch);
    fixed: once per process, in RAM (cpu: its threads' scratch MjData).
    """

    per_world: int
    fixed: int = 0


def mjdata_bytes(m: mujoco.MjModel) -> int:
    """Bytes in one MjData's arrays (not its arena): the size of a world's state and outputs."""
    d = mujoco.MjData(m)
    total = 0
    for name in dir(d):
        if not name.startswith("_"):
            value = getattr(d, name, None)
            if isinstance(value, np.ndarray):
                total += value.nbytes
    return total


def fleet_memory(
    spec: RobotSpec,
    backend: str,
    nworld: int,
    physics: PhysicsMemory,
    *,
    ros: bool,
    on_device: bool = False,
    controllers: bool = False,
    ros_workers: int = 1,
) -> MemoryEstimate:
    """What `nworld` worlds of `spec` on `backend` (its name, for messages) will take, the
    backend's physics as its class states it (batchsim.backends.estimate_memory asks it).

    Args:
      ros: the ROS 2 bridge runs (ROS_BRIDGE_BYTES_PER_WORLD a world, ROS_BRIDGE_BYTES_PER_WORKER
        for each of its `ros_workers` processes; 0 workers, in-process, cost one's baseline).
      on_device: the backend runs on a GPU: its physics counts against device memory.
      controllers: ros2_control-style controllers run in every world.
    """
    m = spec.mjmodel
    row = mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_FULLPHYSICS) + m.nq + m.nv + m.nu + m.nsensordata
    host_arrays = int(HOST_ROW_FACTOR * 8 * row)
    ros_fixed = ROS_BRIDGE_BYTES_PER_WORKER * max(1, ros_workers) if ros else 0
    fixed = FIXED_HOST_BYTES + physics.fixed + ros_fixed
    ros_per_world = ROS_BRIDGE_BYTES_PER_WORLD if ros else 0
    controllers_per_world = CONTROLLER_BYTES_PER_COMMAND * len(spec.commands) if controllers else 0
    if on_device:
        host = fixed + nworld * (host_arrays + ros_per_world + controllers_per_world)
        device = nworld * physics.per_world
        per_world = physics.per_world
    else:
        per_world = host_arrays + physics.per_world
        host = fixed + nworld * (per_world + ros_per_world + controllers_per_world)
        device = 0
    return MemoryEstimate(nworld, backend, host, device, per_world, ros_per_world, fixed, controllers_per_world, ros_fixed)


def available_host_memory() -> int | None:
    """MemAvailable from /proc/meminfo in bytes; None where there is none (not Linux)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


_WAY_OUT = "use fewer worlds{ros}, or --skip-memory-check to try anyway"


def check_host_memory(estimate: MemoryEstimate, available: int | None = None) -> str | None:
    """Refuse a fleet whose RAM estimate exceeds `available` (None: MemAvailable now).

    Returns:
      None, or a warning line when the estimate is above WARN_FRACTION of what is available.
    Raises:
      MemoryCheckError: the estimate exceeds what is available.
    """
    if available is None:
        available = available_host_memory()
        if available is None:
            return None
    need = f"{estimate.nworld} worlds need about {_size(estimate.host)} of RAM ({estimate.breakdown()})"
    if estimate.host > available:
        ros = ", --no-ros" if estimate.ros_per_world else ""
        raise MemoryCheckError(f"{need}, but {_size(available)} is available: " + _WAY_OUT.format(ros=ros))
    if estimate.host > WARN_FRACTION * available:
        return f"{estimate.nworld} worlds will take about {_size(estimate.host)} of the {_size(available)} of RAM available"
    return None


def check_device_memory(estimate: MemoryEstimate, memory: DeviceMemory | None) -> str | None:
    """As check_host_memory, for the device; `memory` None (not reported) is not checked."""
    if memory is None or not estimate.device:
        return None
    name = f"{estimate.backend}'s device memory"
    if estimate.device > memory.free:
        raise MemoryCheckError(
            f"{estimate.nworld} worlds need about {_size(estimate.device)} of {name}, but "
            f"{_size(memory.free)} of {_size(memory.total)} is free: " + _WAY_OUT.format(ros="")
        )
    if estimate.device > WARN_FRACTION * memory.free:
        return f"{estimate.nworld} worlds will take about {_size(estimate.device)} of the {_size(memory.free)} of {name} free"
    return None


def device_memory(backend_class: type, device: Any = None) -> DeviceMemory | None:
    """The backend's own report of its device's memory (a `device_memory(device)` static
    method returning (free, total) bytes), or None where the backend has none."""
    report = getattr(backend_class, "device_memory", None)
    if report is None:
        return None
    free_total = report(device)
    return None if free_total is None else DeviceMemory(*map(int, free_total))


def _size(nbytes: float) -> str:
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if nbytes >= scale:
            return f"{nbytes / scale:.1f} {unit}"
    return f"{nbytes / 1e3:.0f} kB"


def install_command(extra: str) -> str:
    """The pip command that installs batchsim's `extra` ("warp", "mjx", "ros") from this
    checkout: batchsim is not on a package index."""
    root = Path(__file__).resolve().parent.parent
    where = str(root) if (root / "pyproject.toml").is_file() else "<your batchsim checkout>"
    return f"pip install -e '{where}[{extra}]'"


# --- progress ---


class Progress:
    """Shows each start-up stage that takes longer than `after` seconds.

    On a terminal, a live line `batchsim: <stage> ... 3 s` redrawn every second (the rest of
    the line cleared), ended by `batchsim: <stage>: done in 3.2 s`; in a log, one line when
    the stage passes `after` and one when it ends. Quicker stages print nothing.
    """

    def __init__(self, stream: TextIO | None = None, *, after: float = 1.0):
        self.stream = stream if stream is not None else sys.stderr
        self.after = after
        try:
            self.tty = self.stream.isatty()
        except (AttributeError, ValueError):
            self.tty = False
        self.current: str | None = None
        self._lock = threading.Lock()
        self._shown = False
        self._live = False  # a terminal line that is not ended yet

    @contextmanager
    def stage(self, what: str) -> Iterator[None]:
        """The stage `what` ("allocating 100000 worlds") runs inside the block."""
        start = time.monotonic()
        done = threading.Event()
        with self._lock:
            self.current, self._shown = what, False
        ticker = threading.Thread(target=self._tick, args=(what, start, done), daemon=True)
        ticker.start()
        ok = False
        try:
            yield
            ok = True
        finally:
            done.set()
            ticker.join()
            with self._lock:
                if self._shown and ok:
                    end = f"batchsim: {what}: done in {time.monotonic() - start:.1f} s"
                    self._write(f"\r{end}\x1b[K\n" if self.tty else end + "\n")
                    self._live = False
                elif self._live and not ok:
                    self._write("\n")  # an error line goes below the live line
                    self._live = False
                if ok:  # a stage left by a signal stays named for the interrupt's line
                    self.current = None

    def _tick(self, what: str, start: float, done: threading.Event) -> None:
        if done.wait(self.after):
            return
        drawn = -1
        while True:
            elapsed = int(time.monotonic() - start)
            with self._lock:
                if done.is_set():
                    return
                if self.tty and elapsed != drawn:
                    self._write(f"\rbatchsim: {what} ... {elapsed} s\x1b[K")
                    self._live, drawn = True, elapsed
                elif not self._shown:
                    self._write(f"batchsim: {what} ...\n")
                self._shown = True
            if not self.tty or done.wait(0.1):
                return

    def _write(self, text: str) -> None:
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):  # a closed pipe must not stop start-up
            pass

    def interrupted(self, signum: int) -> None:
        """The one line for a signal during start-up."""
        with self._lock:
            where = f" ({self.current})" if self.current else ""
            line = f"batchsim: interrupted by {signal.Signals(signum).name} during start-up{where}; nothing ran"
            self._write(("\n" if self._live else "") + line + "\n")
            self._live = False

    def close(self) -> None:
        """End a live line, if one is left."""
        with self._lock:
            if self._live:
                self._write("\n")
                self._live = False


# --- signals during start-up ---


class StartupInterrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived during start-up (raised in the main thread). A
    KeyboardInterrupt, so that code cleaning up after Ctrl-C (bridge workers) does so."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


class StartupGuard:
    """SIGINT/SIGTERM inside the block end the process with one line and 128 + signal.

    Where the main thread returns to Python, the signal unwinds it (finally blocks run) and
    the block's exit raises SystemExit(130 or 143). Where it is inside a library call that
    releases the GIL (mujoco.batch, XLA's compiler, DDS), a watcher thread, woken through
    the signal wakeup fd, waits GRACE seconds and then exits the process itself. A call
    that holds the GIL (MuJoCo compiling a huge MJCF) delays the exit until it returns.
    Use it from the main thread only.
    """

    GRACE = 0.5
    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self, progress: Progress):
        self.progress = progress
        self._left = threading.Event()
        self._reported = threading.Lock()
        self._swallowed: StartupInterrupted | None = None

    def __enter__(self) -> StartupGuard:
        self._reader, self._writer = socket.socketpair()
        self._writer.setblocking(False)
        self._old_fd = signal.set_wakeup_fd(self._writer.fileno(), warn_on_full_buffer=False)
        self._old = {s: signal.signal(s, self._raise) for s in self.SIGNALS}
        # a signal that lands inside a callback Python cannot raise out of (a gc callback,
        # as jax's is, a __del__) is swallowed there: the watcher ends the process instead,
        # and the usual "Exception ignored in" traceback would be a second, misleading line
        self._old_hook = sys.unraisablehook
        sys.unraisablehook = self._unraisable
        self._watcher = threading.Thread(target=self._watch, name="batchsim-startup-guard", daemon=True)
        self._watcher.start()
        return self

    @staticmethod
    def _raise(signum: int, frame: Any) -> None:
        raise StartupInterrupted(signum)

    def _unraisable(self, unraisable: Any) -> None:
        if isinstance(unraisable.exc_value, StartupInterrupted):
            self._swallowed = unraisable.exc_value
        else:
            self._old_hook(unraisable)

    def _watch(self) -> None:
        while True:
            try:
                data = self._reader.recv(1)
            except OSError:
                return
            if not data or self._left.is_set():
                return
            if data[0] not in self.SIGNALS:
                continue
            if self._left.wait(self.GRACE):
                return  # the main thread got there itself
            if self._reported.acquire(blocking=False):
                self.progress.interrupted(data[0])
                os._exit(128 + data[0])

    def __exit__(self, exc_type: Any, exc: BaseException | None, tb: Any) -> None:
        for s, handler in self._old.items():
            signal.signal(s, handler)
        signal.set_wakeup_fd(self._old_fd)
        sys.unraisablehook = self._old_hook
        self._left.set()
        try:
            self._writer.send(b"\0")  # wakes the watcher, which sees the block is left
        except OSError:
            pass
        self._watcher.join(timeout=1.0)
        self._writer.close()
        self._reader.close()
        if exc is None:
            exc = self._swallowed  # the block ended before the watcher's grace did
        if isinstance(exc, StartupInterrupted):
            if self._reported.acquire(blocking=False):
                self.progress.interrupted(exc.signum)
            raise SystemExit(128 + exc.signum) from None
