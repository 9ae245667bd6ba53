"""The loop participant that renders cameras and scans lidars at their rates, only where wanted.

Every control period, for each camera (at the camera rate) and lidar (at its own or the
lidar rate) that is due and wanted in some world (`SensorSuite.want`), it renders or scans
those worlds only, keeps the result as the sensor's latest `Sample`, and hands it to the
listeners (the ROS bridge's publishers, in its second phase). A sensor nobody wants costs
one mask test per period.

Where a render or scan costs in proportion to the worlds it covers (cpu, mjx), the worlds
are spread over the sensor's period: with a 10 Hz camera and a 100 Hz loop, world w is
rendered in the periods k with k % 10 == w % 10, so no period carries the whole fleet's
images (its worst period, not only its mean, stays in budget). Where one launch covers
every world at the same cost (warp: `Contract.sensors_batched`), all wanted worlds are
produced together, and it is the sensors that are spread: a period runs one such launch,
the earliest deadline first, and a sensor due in the same period waits for a later one as
long as it can without missing its next reading (a 30 Hz camera and a 10 Hz lidar at a
100 Hz loop: the lidar one period after the camera they would share; two 100 Hz cameras
still share every period). Either way each world's sensor runs at its rate, rounded to a
whole number of control periods when spread, and every sample is stamped with the sim time
it was taken at.

Cameras on cpu and mjx are rendered with `render_async`: a render thread draws them while
the loop steps the physics, so rendering and physics share two cores instead of queueing
on one. A render is handed to the listeners once it is done, at the next update() or the
one after (its stamp stays the sim time its state was taken at); at most MAX_PENDING
renders wait at once, beyond which update() waits for the oldest, so no frame is dropped.
One update() hands out at most one frame of a world per camera, as the synchronous order
did (the bridge's shared memory holds one sample per world: a second in the same period
would overwrite the first before a worker published it). `flush()` waits for them all.
"""

from __future__ import annotations

import collections
import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from batchsim.loop.sim_loop import Participant

if TYPE_CHECKING:
    from batchsim.contract import Contract
    from batchsim.types import PendingFrames

MAX_PENDING = 4  # renders in flight at once; one is a control period's share of a camera's worlds


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


class SensorSampler(Participant):
    """Produces cameras and lidars inside the loop (a `batchsim.loop` participant).

    Args:
      sim: the system, whose `sensors` say what exists and who wants it.
      listeners: called with each new Sample, in the loop thread.

    Attributes:
      latest: the last Sample of each sensor.
      produced: how many world-frames (or world-scans) each sensor has handed out.
    """

    def __init__(self, sim: Contract, listeners: list[Callable[[Sample], None]] | None = None):
        suite = sim.sensors
        self.listeners = list(listeners or [])
        self.latest: dict[str, Sample] = {}
        self.produced = {name: 0 for name in (*suite.cameras, *suite.lidars)}
        self._period = {name: 1.0 / suite.camera_rate for name in suite.cameras}
        self._period.update({name: 1.0 / (ld.rate or suite.lidar_rate) for name, ld in suite.lidars.items()})
        self._due = dict.fromkeys(self._period, 0.0)
        self._spread = not sim.sensors_batched
        self._world = np.arange(sim.nworld)
        self._pending: collections.deque[tuple[float, PendingFrames]] = collections.deque()  # oldest first
        sim.prepare_rendering()  # the render thread's GL context now, not in a control period

    def update(self, sim: Contract, time: float, period: float) -> None:
        suite = sim.sensors
        batched = []  # (deadline, name, mask) of the batched sensors due now
        for name, every in self._period.items():
            mask = suite.wanted(name)
            if not mask.any():
                continue
            if self._spread:
                phases = max(1, round(every / period))
                mask = mask & (self._world % phases == round(time / period) % phases)
                if mask.any():
                    self._produce(sim, name, np.flatnonzero(mask), time)
            # due once a sensor period has elapsed; half a control period of slack absorbs rounding
            elif time + 0.5 * period >= self._due[name]:
                # the last period it can run in before its next reading is due
                batched.append((self._due[name] + every - period, name, mask))
        batched.sort()
        for i, (deadline, name, mask) in enumerate(batched):
            if i and time + 0.5 * period < deadline:
                continue  # one launch a period: this one in a later period, still before its next reading
            # the next reading one sensor period on from this one's schedule (the rate holds
            # when it waited); after idling or falling behind, from now
            due = self._due[name] + self._period[name]
            self._due[name] = due if due > time else time + self._period[name]
            self._produce(sim, name, np.flatnonzero(mask), time)
        # renders done by now go out, oldest first, past MAX_PENDING the oldest is waited for;
        # but a world's second frame of a camera waits for the next update
        handed: dict[str, np.ndarray] = {}  # per camera, the worlds handed out in this update
        while self._pending:
            job = self._pending[0][1]
            if not (job.done() or len(self._pending) > MAX_PENDING):
                break
            seen = handed.get(job.camera)
            if seen is None:
                seen = handed[job.camera] = np.zeros(len(self._world), bool)
            elif seen[job.worlds].any():
                break
            seen[job.worlds] = True
            self._deliver(*self._pending.popleft())

    def flush(self) -> None:
        """Wait for every render still in flight and hand it to the listeners."""
        while self._pending:
            self._deliver(*self._pending.popleft())

    def on_stop(self, sim: Contract, time: float) -> None:
        """The run is over: its renders still in flight go out now, not never (a recording's last frames)."""
        self.flush()

    def _produce(self, sim: Contract, name: str, worlds: np.ndarray, time: float) -> None:
        if name in sim.sensors.cameras:
            if self._spread:
                self._pending.append((time, sim.render_async(name, worlds)))
            else:  # drawn before render returns: handed out as they are, no thread, no copy of the frames
                rgb, depth = sim.render(name, worlds, copy=False)
                self._hand_out(Sample(name, time, worlds, rgb=rgb, depth=depth))
        else:
            self._hand_out(Sample(name, time, worlds, ranges=sim.scan(name, worlds, copy=False)))

    def _deliver(self, time: float, job: PendingFrames) -> None:
        rgb, depth = job.result()
        self._hand_out(Sample(job.camera, time, job.worlds, rgb=rgb, depth=depth))

    def _hand_out(self, sample: Sample) -> None:
        self.produced[sample.name] += len(sample.worlds)
        self.latest[sample.name] = sample
        for listener in self.listeners:
            listener(sample)
