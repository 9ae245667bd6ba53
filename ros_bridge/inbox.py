"""Commands received on ROS threads, checked there, applied in the loop thread.

ROS callbacks only call `put_vector` / `put_single` / `reject`: each checks the message,
stores it under a lock and returns. The loop thread calls `take` once per control
period to copy what arrived into the system's `command` array. So the simulation is
never touched from a ROS thread, and a flood of messages costs the loop one lock and one
copy per period, however many arrived.

No rclpy here: the rules are testable without a ROS graph.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from collections.abc import Sequence

import numpy as np

from batchsim.hardware import MAX_COMMAND


@dataclasses.dataclass(frozen=True)
class Rejection:
    """A command that was not applied: which world, on which topic, and why."""

    world: int
    topic: str
    problem: str
    controller: str = ""  # set when the interface is claimed by a controller


class CommandInbox:
    """The latest commands per world and interface, between ROS threads and the loop.

    Args:
      nworld: number of worlds.
      interfaces: command interface names, in `command` column order.
    """

    def __init__(self, nworld: int, interfaces: Sequence[str]):
        self.nworld = nworld
        self.interfaces = list(interfaces)
        ncommand = len(self.interfaces)
        self._lock = threading.Lock()
        self._arrived = threading.Condition(self._lock)
        self._value = np.zeros((nworld, ncommand))
        self._new = np.zeros((nworld, ncommand), dtype=bool)
        self._rejections: list[Rejection] = []
        # column -> controller that owns it; raw topics may not write these
        self._owner: list[str] = [""] * ncommand
        self._free = np.ones(ncommand, dtype=bool)
        self.received = 0  # messages accepted, for the benchmark and diagnostics

    # --- controllers' claims (loop or main thread) ---
    def claim(self, controller: str, interfaces: Sequence[str]) -> None:
        """Reserve `interfaces` for `controller`: raw topic commands to them are rejected."""
        cols = []
        for name in interfaces:
            if name not in self.interfaces:
                raise ValueError(
                    f"controller {controller!r} claims {name!r}, which is not a command interface "
                    f"(command interfaces: {', '.join(self.interfaces)})"
                )
            c = self.interfaces.index(name)
            if self._owner[c] and self._owner[c] != controller:
                raise ValueError(
                    f"controller {controller!r} claims {name!r}, which controller "
                    f"{self._owner[c]!r} already owns"
                )
            cols.append(c)
        with self._lock:
            for c in cols:
                self._owner[c] = controller
                self._free[c] = False
                self._new[:, c] = False

    def release(self, controller: str) -> None:
        """Give back every interface `controller` claimed."""
        with self._lock:
            for c, owner in enumerate(self._owner):
                if owner == controller:
                    self._owner[c] = ""
                    self._free[c] = True

    def owner(self, interface: str) -> str:
        """The controller that claimed `interface`, or ""."""
        return self._owner[self.interfaces.index(interface)]

    @property
    def free(self) -> np.ndarray:
        """(ncommand,) bool: the interfaces raw topics may command."""
        return self._free

    # --- ROS threads ---
    def put_vector(self, world: int, data: Sequence[float], topic: str) -> bool:
        """A whole command row for one world (the `commands` topic); False if rejected."""
        n = len(self.interfaces)
        if len(data) != n:
            return self.reject(
                world,
                topic,
                f"{len(data)} values, expected {n} (one per command interface: {', '.join(self.interfaces)})",
            )
        row = np.asarray(data, dtype=np.float64)
        if not np.isfinite(row).all():
            bad = int(np.flatnonzero(~np.isfinite(row))[0])
            return self.reject(world, topic, f"value {row[bad]} for {self.interfaces[bad]} is not finite")
        if (np.abs(row) >= MAX_COMMAND).any():
            bad = int(np.flatnonzero(np.abs(row) >= MAX_COMMAND)[0])
            return self.reject(world, topic, f"value {row[bad]:g} for {self.interfaces[bad]} is beyond {MAX_COMMAND:g}")
        if not self._free.all():
            owners = sorted({o for o in self._owner if o})
            return self.reject(
                world,
                topic,
                "interfaces are claimed by controller " + ", ".join(repr(o) for o in owners),
                controller=", ".join(owners),
            )
        with self._lock:
            self._value[world] = row
            self._new[world] = True
            self.received += 1
            self._arrived.notify_all()
        return True

    def put_single(self, world: int, column: int, value: float, topic: str) -> bool:
        """One interface's command for one world (an `actuators/<a>/command` topic)."""
        if not math.isfinite(value):
            return self.reject(world, topic, f"value {value} is not finite")
        if abs(value) >= MAX_COMMAND:
            return self.reject(world, topic, f"value {value:g} is beyond {MAX_COMMAND:g}")
        owner = self._owner[column]
        if owner:
            return self.reject(
                world, topic, f"{self.interfaces[column]} is claimed by controller {owner!r}", controller=owner
            )
        with self._lock:
            self._value[world, column] = value
            self._new[world, column] = True
            self.received += 1
            self._arrived.notify_all()
        return True

    def reject(self, world: int, topic: str, problem: str, controller: str = "") -> bool:
        with self._lock:
            if len(self._rejections) < 1000:  # a flood of bad messages must not grow without bound
                self._rejections.append(Rejection(world, topic, problem, controller))
        return False

    # --- loop thread ---
    def take(self, command: np.ndarray) -> tuple[np.ndarray | None, list[Rejection]]:
        """Copy what arrived into `command` (nworld, ncommand) in place.

        Returns the worlds that got a command ((nworld,) bool, or None if none did) and
        the rejections since the last call.
        """
        with self._lock:
            rejections = self._rejections
            if rejections:
                self._rejections = []
            if not self._new.any():
                return None, rejections
            new = self._new
            np.copyto(command, self._value, where=new)
            worlds = new.any(axis=1)
            new[:] = False
        return worlds, rejections

    def clear(self, worlds: np.ndarray | None = None) -> None:
        """Drop what arrived for all or the listed worlds (they were reset)."""
        with self._lock:
            if worlds is None:
                self._new[:] = False
            else:
                self._new[worlds] = False

    def wait_ready(self, timeout: float) -> np.ndarray:
        """Lockstep: wait up to `timeout` s until every world has a command for every free
        interface; return (nworld,) bool, the worlds that have one."""
        with self._lock:
            ready = self._ready()
            if not ready.all() and timeout > 0:
                self._arrived.wait(timeout)
                ready = self._ready()
            return ready

    def _ready(self) -> np.ndarray:
        free = self._free
        if not free.any():
            return np.ones(self.nworld, dtype=bool)
        return self._new[:, free].all(axis=1)
