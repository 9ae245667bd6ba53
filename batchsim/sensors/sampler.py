"""The loop participant that renders cameras and scans lidars at their rates, only where wanted.

Every control period, for each camera (at the camera rate) and lidar (at its own or the
lidar rate) that is due and wanted in some world (`SensorSuite.want`), it renders or scans
those worlds only, keeps the result as the sensor's latest `Sample`, and hands it to the
listeners (the ROS bridge's publishers, in its second phase). A sensor nobody wants costs
one mask test per period.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from batchsim.hardware import BatchedSystem


@dataclasses.dataclass(frozen=True)
class Sample:
    """One sensor's output for some worlds at one sim time; the arrays may be buffers that the
    sensor's next sample overwrites (copy them to keep them).

    Attributes:
      name: the camera or lidar.
      time: sim time of the reading (seconds), for the message stamps.
      worlds: (n,) the worlds it was produced for, ascending.
      rgb: (n, H, W, 3) uint8 (cameras), else None.
      depth: (n, H, W) float32 metres (cameras), else None.
      ranges: (n, nray) float32 metres, REP 117 (lidars), else None.
    """

    name: str
    time: float
    worlds: np.ndarray
    rgb: np.ndarray | None = None
    depth: np.ndarray | None = None
    ranges: np.ndarray | None = None


class SensorSampler:
    """Produces cameras and lidars inside the loop (a `batchsim.loop` participant).

    Args:
      sim: the system, whose `sensors` say what exists and who wants it.
      listeners: called with each new Sample, in the loop thread.

    Attributes:
      latest: the last Sample of each sensor.
      produced: how many world-frames (or world-scans) each sensor has produced.
    """

    def __init__(self, sim: BatchedSystem, listeners: list[Callable[[Sample], None]] | None = None):
        suite = sim.sensors
        self.listeners = list(listeners or [])
        self.latest: dict[str, Sample] = {}
        self.produced = {name: 0 for name in (*suite.cameras, *suite.lidars)}
        self._period = {name: 1.0 / suite.camera_rate for name in suite.cameras}
        self._period.update({name: 1.0 / (ld.rate or suite.lidar_rate) for name, ld in suite.lidars.items()})
        self._due = dict.fromkeys(self._period, 0.0)

    def update(self, sim: BatchedSystem, time: float, period: float) -> None:
        suite = sim.sensors
        for name, every in self._period.items():
            # due once a sensor period has elapsed; half a control period of slack absorbs rounding
            if time + 0.5 * period < self._due[name]:
                continue
            mask = suite.wanted(name)
            if not mask.any():
                continue
            # the next reading one sensor period on; after idling or falling behind, from now
            due = self._due[name] + every
            self._due[name] = due if due > time else time + every
            worlds = np.flatnonzero(mask)
            if name in suite.cameras:
                rgb, depth = sim.render(name, worlds, copy=False)
                sample = Sample(name, time, worlds, rgb=rgb, depth=depth)
            else:
                sample = Sample(name, time, worlds, ranges=sim.scan(name, worlds))
            self.produced[name] += len(worlds)
            self.latest[name] = sample
            for listener in self.listeners:
                listener(sample)
