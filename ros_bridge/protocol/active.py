"""Which controllers are active in each world (`cm.active`, (nworld, ncontroller) u1, columns
in ManagerSpec.controllers' order): written by the loop as the controller manager switches
(`ActiveWriter`), read by the workers' controller_manager services and action servers
(`ActiveReader`). No rclpy here.
"""

from __future__ import annotations

import numpy as np

from batchsim.memory import Memory


def active_arrays(nworld: int, ncontroller: int) -> list[tuple[str, tuple[int, ...], str]]:
    return [("cm.active", (nworld, max(1, ncontroller)), "u1")]


class ActiveWriter:
    """The loop's side."""

    def __init__(self, memory: Memory):
        self._active = memory["cm.active"]

    def set(self, controller: int, worlds: np.ndarray | slice, on: bool | np.ndarray) -> None:
        """Controller `controller` is active (`on`) in `worlds`, or not."""
        self._active[worlds, controller] = on


class ActiveReader:
    """A worker's side."""

    def __init__(self, memory: Memory):
        self._active = memory["cm.active"]

    def active(self, world: int, controller: int) -> bool:
        return bool(self._active[world, controller])

    def row(self, world: int) -> np.ndarray:
        """(ncontroller,) bool: the controllers active in `world`."""
        return self._active[world].astype(bool)
