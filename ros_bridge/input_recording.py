"""What a recording keeps so that its worlds can be re-run (batchsim.resim): the loop's side. Every
control period, right after write() (where ctrl is what the steps take), the recorded worlds'
physics inputs and command interfaces go into the input ring; in the recording's first period and
after each reset, the (re)starting worlds' whole physics state and draws go into the start ring
(ros_bridge/protocol/input_ring.py). Every message the controllers take (a command topic's rows, a
trajectory or a goal's: `Input.apply`) goes, for the recorded worlds, into the event ring as a JSON
document (`InputTap`), so that `batchsim resim --controllers` re-runs the controllers too. The
recorder writes them as `/batchsim/inputs`, `/batchsim/starts` and `/batchsim/controller_inputs`,
with the model's MJB (`source`). No rclpy here.
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import json
import time as wallclock
from collections.abc import Callable

import mujoco
import numpy as np

from batchsim.controllers.topics import Input, MessageKind
from batchsim.memory import Ring
from batchsim.resim.layout import InputsLayout, effort_sources, layout_of, model_bytes, model_hash
from ros_bridge.protocol.input_ring import EVENTS, INPUTS, STARTS, RowRing
from ros_bridge.protocol.recording import recording


def inputs_layout(sim) -> InputsLayout | None:
    """What re-simulation records of `sim` (configured) each period; None where it cannot (a fleet
    over several devices)."""
    try:
        base = sim.base_velocity
        held = (base.qposadr, base.dofadr) if base is not None else (-1, -1)
        return layout_of(sim.model, sim.physics_inputs([0]), sim.world_params([0]), held, sim.command.shape[1])
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
        self._every = np.array_equal(self._worlds, np.arange(plan.nworld))
        self._row = np.full(plan.nworld, -1, np.intp)
        self._row[self._worlds] = np.arange(len(self._worlds))
        self._inputs, self._starts = RowRing(memory, INPUTS), RowRing(memory, STARTS)
        self._events, self._dropped = Ring(memory, EVENTS), memory[f"{EVENTS}.dropped"]
        self.memory = memory
        self._need_start = np.ones(len(self._worlds), bool)  # recorded worlds whose start is yet to be recorded
        self._fresh = np.zeros(len(self._worlds), bool)  # worlds reset since their last start
        self._periods = 0  # periods recorded since the recording began
        self._time = 0.0  # the sim time of the period under way

    def restart(self) -> None:
        """A new recording: the rings emptied, every world's start due, period 0 next."""
        self._inputs.restart()
        self._starts.restart()
        self._events.pos[1] = self._events.pos[0]
        self._dropped[0] = 0
        self._need_start[:] = True
        self._fresh[:] = False
        self._periods = 0

    def source(self, group: str = "") -> dict:
        """What the file holds beside the rings' topics: the model's MJB, and the run's facts (the
        `batchsim_resim` metadata record; in a fleet of several groups, one per group, naming it)."""
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
                "group": group,
                # where each joint's effort is read from (the engine field, its index, the sign): resim compares it
                "effort": json.dumps(effort_sources(sim.spec.state)),
            },
        }

    def after_write(self, sim, time: float, period: float) -> None:
        """This period's inputs, and the starts due, into the rings."""
        header = (float(self._periods), time, float(round(period / sim.dt)))
        self._periods += 1
        self._time = time
        worlds = self._worlds
        if self._need_start.any():
            rows = np.flatnonzero(self._need_start)
            fresh = self._fresh[rows] | (time == 0.0)  # a reset, or the run's first period
            self._need_start[rows] = self._fresh[rows] = False
            chosen = worlds[rows]
            starts = self.layout.start_row(
                self.plan.world_offset + chosen, sim.draw_numbers()[chosen], fresh, sim.physics_state(chosen),
                sim.world_params(chosen),
            )  # fmt: skip
            for row in starts:
                self._wait_for(self._starts)
                self._starts.put(header, row[None])
        every = self._every  # every world recorded: whole arrays, no index (this runs every period)
        inputs = sim.physics_inputs(None if every else worlds)
        inputs["command"] = sim.command if every else sim.command[worlds]
        self._wait_for(self._inputs)
        self._inputs.put(header, self.layout.input_row(sim.frozen if every else sim.frozen[worlds], inputs))

    def event(self, topic: str, worlds: np.ndarray, rows: np.ndarray | None = None, batch=None) -> None:
        """A controller input (InputTap): `rows` (n, width) for `worlds`, or a TrajectoryBatch;
        the recorded worlds' part into the event ring, tagged with the period whose update takes
        it (one handed over beside the steps: the next)."""
        if not recording(self.memory):
            return
        worlds = np.asarray(batch.worlds if batch is not None else worlds)
        rec = self._row[worlds] >= 0
        if not rec.any():
            return
        doc = {"period": self._periods, "time": self._time, "topic": topic}
        if batch is not None:
            doc["batch"] = batch_document(batch.select(rec), self.plan.world_offset)
        else:
            doc["worlds"] = (self.plan.world_offset + worlds[rec]).tolist()
            doc["rows"] = np.asarray(rows)[rec].tolist()
        self._put(doc)

    def control(self, kind: str, world: int, what: dict) -> None:
        """A switch, parameter set, goal cancel or gripper goal in `world` (ManagerLink's), where recorded."""
        if recording(self.memory) and self._row[world] >= 0:
            self._put({"period": self._periods, "time": self._time, "kind": kind, "world": self.plan.world_offset + world, **what})

    def _put(self, doc: dict) -> None:
        if not self._events.put(1, json.dumps(doc).encode()):
            self._dropped[0] += 1

    def on_reset(self, worlds: np.ndarray | None) -> None:
        """A reset world's next period records its start (its state and draws) again, afresh."""
        rows = slice(None) if worlds is None else self._row[worlds][self._row[worlds] >= 0]
        self._need_start[rows] = self._fresh[rows] = True

    def _wait_for(self, ring: RowRing) -> None:
        """With `--rtf 0`, until the recorder made room in `ring` (every period gets in)."""
        if self.loop.rtf == 0:
            while ring.full() and self._alive():
                wallclock.sleep(0.0005)


def batch_document(batch, offset: int) -> dict:
    """A TrajectoryBatch as JSON-ready lists (worlds as fleet numbers; None kept), exact: JSON
    writes a float64 by its shortest repr, which reads back to the same bits."""
    doc = {f.name: (None if (v := getattr(batch, f.name)) is None else np.asarray(v).tolist()) for f in dataclasses.fields(batch)}
    doc["worlds"] = (offset + np.asarray(batch.worlds)).tolist()
    return doc


class InputTap:
    """The controllers' command inputs as the loop hands them over: `wrap(inputs)` gives inputs
    whose `apply` first tells `target` (an InputRecording, set once it exists; None: nobody), and
    `control` passes on the ManagerLink's switches, parameter sets, cancels and gripper goals."""

    def __init__(self) -> None:
        self.target: InputRecording | None = None

    def control(self, kind: str, world: int, what: dict) -> None:
        if self.target is not None:
            self.target.control(kind, world, what)

    def wrap(self, inputs: list[Input]) -> list[Input]:
        return [dataclasses.replace(inp, apply=self._tapped(inp)) for inp in inputs]

    def _tapped(self, inp: Input) -> Callable:
        apply, topic = inp.apply, inp.topic
        if inp.kind is MessageKind.JOINT_TRAJECTORY:

            def tapped_batch(batch):
                if self.target is not None:
                    self.target.event(topic, batch.worlds, batch=batch)
                return apply(batch)

            return tapped_batch

        def tapped(worlds, rows):
            if self.target is not None:
                self.target.event(topic, worlds, rows)
            return apply(worlds, rows)

        return tapped
