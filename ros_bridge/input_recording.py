"""What a recording keeps so that its worlds can be re-run (batchsim.resim): the loop's side. Every
control period, right after write() (where ctrl is what the steps take), the recorded worlds'
physics inputs go into the input ring; in the recording's first period and after each reset, the
(re)starting worlds' whole physics state and draws go into the start ring
(ros_bridge/protocol/input_ring.py). The recorder writes them as `/batchsim/inputs` and
`/batchsim/starts`, with the model's MJB (`source`). No rclpy here.
"""

from __future__ import annotations

import importlib.metadata
import json
import time as wallclock
from collections.abc import Callable

import mujoco
import numpy as np

from batchsim.resim.layout import InputsLayout, layout_of, model_bytes, model_hash
from ros_bridge.protocol.input_ring import INPUTS, STARTS, RowRing


def inputs_layout(sim) -> InputsLayout | None:
    """What re-simulation records of `sim` (configured) each period; None where it cannot (a fleet
    over several devices)."""
    try:
        base = sim.base_velocity
        held = (base.qposadr, base.dofadr) if base is not None else (-1, -1)
        return layout_of(sim.model, sim.physics_inputs([0]), sim.world_params([0]), held)
    except NotImplementedError:
        return None


def _version() -> str:
    try:
        return importlib.metadata.version("batchsim")
    except importlib.metadata.PackageNotFoundError:  # a checkout run without an install
        return "unknown"


class InputRecording:
    """The input and start rings' writer, owned by a Recording (ros_bridge/recording.py), for
    `plan.recording`'s worlds; `alive()` says whether the recorder still takes entries."""

    def __init__(self, plan, memory, loop, alive: Callable[[], bool]):
        self.plan, self.loop, self._alive = plan, loop, alive
        self.layout: InputsLayout = plan.recording.inputs
        self._worlds = np.array(plan.recording.worlds, np.intp)
        self._row = np.full(plan.nworld, -1, np.intp)
        self._row[self._worlds] = np.arange(len(self._worlds))
        self._inputs, self._starts = RowRing(memory, INPUTS), RowRing(memory, STARTS)
        self._need_start = np.ones(len(self._worlds), bool)  # recorded worlds whose start is yet to be recorded
        self._periods = 0  # periods recorded since the recording began

    def restart(self) -> None:
        """A new recording: the rings emptied, every world's start due, period 0 next."""
        self._inputs.restart()
        self._starts.restart()
        self._need_start[:] = True
        self._periods = 0

    def source(self) -> dict:
        """What the file holds beside the rings' topics: the model's MJB, and the run's facts (the
        `batchsim_resim` metadata record)."""
        sim = self.loop.sim
        data = model_bytes(sim.model)
        worlds = self.plan.recording.worlds
        return {
            "model": data,
            "meta": {
                "layout": self.layout.to_json(),
                "model_sha256": model_hash(data),
                "backend": sim.name,
                "mujoco": mujoco.__version__,
                "batchsim": _version(),
                "timestep": repr(sim.dt),
                "worlds": json.dumps([self.plan.world_offset + w for w in worlds]),
                "namespaces": json.dumps([self.plan.namespaces[w] for w in worlds]),
            },
        }

    def after_write(self, sim, time: float, period: float) -> None:
        """This period's inputs, and the starts due, into the rings."""
        header = (float(self._periods), time, float(round(period / sim.dt)))
        self._periods += 1
        worlds = self._worlds
        if self._need_start.any():
            rows = np.flatnonzero(self._need_start)
            self._need_start[rows] = False
            chosen = worlds[rows]
            starts = self.layout.start_row(
                self.plan.world_offset + chosen, sim.draw_numbers()[chosen], sim.physics_state(chosen), sim.world_params(chosen)
            )
            for row in starts:
                self._wait_for(self._starts)
                self._starts.put(header, row[None])
        self._wait_for(self._inputs)
        self._inputs.put(header, self.layout.input_row(sim.frozen[worlds], sim.physics_inputs(worlds)))

    def on_reset(self, worlds: np.ndarray | None) -> None:
        """A reset world's next period records its start (its state and draws) again."""
        if worlds is None:
            self._need_start[:] = True
        else:
            rows = self._row[worlds]
            self._need_start[rows[rows >= 0]] = True

    def _wait_for(self, ring: RowRing) -> None:
        """With `--rtf 0`, until the recorder made room in `ring` (every period gets in)."""
        if self.loop.rtf == 0:
            while ring.full() and self._alive():
                wallclock.sleep(0.0005)
