"""What the warp engine's helpers share: its worlds on the device (`DeviceWorlds`: MuJoCo Warp's
Model and Data and the per-world arrays beside them) and the graphs captured on them (`Graphs`).

The engine makes one DeviceWorlds at open and hands it to each helper it owns (transfers,
period, reset, poses, sensors, ...); when the buffers grow it puts the new Data in `d`, so
every helper launches on the current one, and drops the graphs captured on the old.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import mujoco
import warp as wp


@dataclasses.dataclass(eq=False)
class DeviceWorlds:
    """The engine's worlds on its device.

    Attributes:
      model: the MjModel; m: MuJoCo Warp's Model of it; d: its Data, replaced when buffers grow
        (the arrays `device_arrays()` hands out are carried into the new one).
      device: the Warp device; cuda: whether it is a GPU; nworld: the number of worlds.
      clock: (nworld,) float64, each world's clock (MuJoCo Warp's `d.time` is float32).
      parked: (nworld,) int32, non-zero for a parked (frozen) world: its ctrl stays zero.
      mask: (nworld,) bool, the worlds a reset or a restore applies to, written before each.
    """

    model: mujoco.MjModel
    m: Any
    d: Any
    device: Any
    nworld: int
    clock: wp.array
    parked: wp.array
    mask: wp.array
    cuda: bool = dataclasses.field(init=False)

    def __post_init__(self) -> None:
        self.cuda = bool(self.device.is_cuda)


class Graphs:
    """Graphs captured on one Data's arrays, by key (a period's by its nstep; the transfers' and
    the reset's by name); `clear()` drops them when the buffers grow and the arrays are new.

    Attributes:
      device: where they launch; cuda: whether it is a GPU.
      enabled: the engine's `graph` option (False: launch kernels one by one, for debugging).
    """

    def __init__(self, device: Any, enabled: bool):
        self.device = device
        self.cuda = bool(device.is_cuda)
        self.enabled = bool(enabled)
        self._captured: dict[Any, Any] = {}

    def get(self, key: Any) -> Any:
        """The graph captured under `key`, or None."""
        return self._captured.get(key)

    def capture(self, key: Any, program: Callable[[], None]) -> Any:
        """`program()`'s launches captured under `key` (recorded, not run): the graph."""
        with wp.ScopedCapture(device=self.device) as capture:
            program()
        graph = self._captured[key] = capture.graph
        return graph

    def replay(self, key: Any) -> bool:
        """Launch the graph captured under `key` on a CUDA device, if there is one: True. A graph
        names its device and stream, so no ScopedDevice is entered (~10 us each, three a period)."""
        graph = self._captured.get(key) if self.cuda else None
        if graph is None:
            return False
        wp.capture_launch(graph)
        return True

    def run(self, key: Any, kernels: Callable[[], None]) -> None:
        """`kernels()` as a graph replayed (CUDA, graphs on), else called. The first call runs them
        uncaptured before capturing them: it loads their modules, which a capture must not."""
        if not (self.cuda and self.enabled):
            kernels()
            return
        graph = self._captured.get(key)
        if graph is None:
            kernels()
            graph = self.capture(key, kernels)
        wp.capture_launch(graph)

    def clear(self) -> None:
        self._captured.clear()
