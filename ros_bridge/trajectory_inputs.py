"""The controllers' trajectory inputs on the physics side: JointTrajectory topics and
FollowJointTrajectory goals, from the workers' rings to their controllers.

A period's trajectories are taken from the rings in the bridge's update() and handed to their
controllers (`Input.apply`: validated and queued; 2.2-2.9 ms for 4096 10-point trajectories on
the 2-core VM, 2.4-5.4 ms on the GPU hosts) while the device steps (BridgeHost.while_stepping),
not on the period's critical path: ros2_control's JointTrajectoryController likewise takes a
message in its subscriber's callback, outside the control loop, and starts it at its next
update. So a trajectory stamped zero starts at the next period's update, one period after the
one whose update took it from the ring.

Where the loop does not step, or must not wait for it, the hand-over is at once: under lockstep
(a world's trajectory then starts in the period its arrival let begin), while paused, in the
lockstep gate, and when the same read holds a controller switch (which resets its controllers
before the steps: what came before it must be there to be dropped) or a goal's cancel (served
after the read's trajectories, so that it finds the goal it cancels). A batch not yet handed
over when the next period, the gate or a pause comes is handed over then, first: none is lost.
A goal's trajectory a reset drops before its controller had it is refused (protocol/goals.py),
as is one its controller refuses, so that its worker aborts the goal at once.

A controller's verdicts on a batch handed over while the device steps reach BAD_COMMAND in the
next update (`verdicts`), as though the trajectories had arrived then: accepted ones count as the
world's good command, refused ones set the flag (while paused, at once).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from batchsim.controllers.topics import Input, MessageKind, Rejections, TrajectoryBatch
from batchsim.memory import Memory
from ros_bridge.protocol.goals import Refusal, RefusalWriter
from ros_bridge.protocol.requests import concatenate

#: (input index, its worlds, the controller's rejections, good, rejected): the bridge's refusal bookkeeping
Refused = Callable[[int, np.ndarray, Rejections, np.ndarray | None, np.ndarray | None], None]


class TrajectoryInputs:
    """The trajectory batches a period took from the rings, until their controllers have them.

    Args:
      memory: the bridge's shared memory (each input's `<slots>.seq` arrival counters; the goal
        refusals, where the fleet serves actions).
      kinds, slots: per plan input, its MessageKind and its slots' name.
      inputs: per plan input, the controller's Input (its `apply`).
      refused: the bridge's bookkeeping of a controller's rejections (logged, counted, BAD_COMMAND).
      nworld: the fleet's worlds.
    """

    def __init__(
        self,
        memory: Memory,
        kinds: Sequence[MessageKind],
        slots: Sequence[str],
        inputs: Sequence[Input],
        refused: Refused,
        nworld: int,
    ):
        self._refusals = RefusalWriter(memory) if "goal.refused" in memory else None
        self._inputs = list(inputs)
        self._refused = refused
        # arrival counters the workers move when a batch is in the ring
        self.counters = {
            i: memory[f"{s}.seq"]
            for i, (k, s) in enumerate(zip(kinds, slots, strict=True))
            if k is MessageKind.JOINT_TRAJECTORY
        }
        self.seen = {i: c.copy() for i, c in self.counters.items()}  # at the last period start
        self.taken = {i: c.copy() for i, c in self.counters.items()}  # as far as the rings were read
        self._waiting: list[tuple[int, TrajectoryBatch]] = []
        # the verdicts of hand-overs beside the steps, for the next update
        self._good = np.zeros(nworld, dtype=bool)
        self._rejected = np.zeros(nworld, dtype=bool)

    @property
    def waiting(self) -> int:
        """Batches taken and not yet handed over."""
        return len(self._waiting)

    def take(
        self,
        batches: dict[int, list[TrajectoryBatch]],
        reset_rows: np.ndarray | None,
        reset: bool,
        good: np.ndarray | None,
        rejected: np.ndarray | None,
        *,
        later: bool,
    ) -> None:
        """A ring read's batches per input: handed over now, or `later` (hand_over, while the
        device steps). A trajectory that arrived with a reset (`reset`: of `reset_rows`, None:
        every world) does not survive it. `good`, `rejected`: this update's arrays (None: the
        bridge's own flag, as while paused). Call hand_over first, before the read's resets: a
        batch an earlier period left waiting goes before them."""
        for index, parts in batches.items():
            batch = concatenate(parts)
            self.taken[index] = self.counters[index].copy()  # read after the ring: never ahead of it
            if reset:
                keep = (
                    np.zeros(len(batch), bool) if reset_rows is None else ~np.isin(batch.worlds, reset_rows)
                )
                if not keep.all():
                    self._dropped(batch, keep)
                    batch = batch.select(keep)
            if len(batch):
                self._waiting.append((index, batch))
        if not later:
            self.hand_over(good, rejected)

    def hand_over(
        self,
        good: np.ndarray | None = None,
        rejected: np.ndarray | None = None,
        *,
        beside_steps: bool = False,
    ) -> None:
        """Give the waiting batches to their controllers. Verdicts go to `good` and `rejected`
        (None: the bridge's own flag, as while paused), or `beside_steps`, while the device steps,
        are kept for the next update's `verdicts`."""
        if not self._waiting:
            return
        waiting, self._waiting = self._waiting, []
        if beside_steps:
            good, rejected = self._good, self._rejected
        for index, batch in waiting:
            refused = self._inputs[index].apply(batch)
            if good is not None:
                good[batch.worlds] = True
            self._refused(index, batch.worlds, refused, good, rejected)
            if batch.goals is not None and refused:  # goals the controller refused: their workers answer
                goals = [(k, reason) for k, reason in refused if batch.goals[k]]
                if goals:
                    at = np.array([k for k, _ in goals], dtype=np.intp)
                    self._refusals.refuse(batch.worlds[at], batch.goals[at], Refusal.INVALID, [r for _, r in goals])

    def verdicts(self, good: np.ndarray, rejected: np.ndarray) -> None:
        """Into this update's arrays: the verdicts of the hand-overs since the last update."""
        if self._good.any() or self._rejected.any():
            good |= self._good
            rejected |= self._rejected
            self._good[:] = False
            self._rejected[:] = False

    def period_starts(self) -> None:
        """This period's trajectories, for the next lockstep wait."""
        for i, taken in self.taken.items():
            self.seen[i] = taken.copy()

    def forget(self, rows: slice | np.ndarray, inputs: set[int] | None = None) -> None:
        """Worlds were reset (`rows`: their indices, or slice(None): every world): their arrivals
        are seen, their waiting trajectories and verdicts dropped; with `inputs`, those of these
        inputs only (one robot of the worlds was reset: its controllers' inputs)."""
        every = isinstance(rows, slice)
        kept = []
        for index, batch in self._waiting:
            keep = np.ones(len(batch), bool) if inputs is not None and index not in inputs else (
                np.zeros(len(batch), bool) if every else ~np.isin(batch.worlds, rows)
            )
            if not keep.all():
                self._dropped(batch, keep)
                batch = batch.select(keep)
            if len(batch):
                kept.append((index, batch))
        self._waiting = kept
        for i, counter in self.counters.items():
            if inputs is None or i in inputs:
                self.seen[i][rows] = counter[rows]
                self.taken[i][rows] = counter[rows]
        if inputs is None:
            self._good[rows] = False
            self._rejected[rows] = False

    def _dropped(self, batch: TrajectoryBatch, keep: np.ndarray) -> None:
        """The goals among the trajectories a reset drops (not `keep`) are refused: their workers
        abort them now, as the controller aborts the goal a reset world was running."""
        if batch.goals is not None:
            at = np.flatnonzero(~keep & (np.asarray(batch.goals) != 0))
            if at.size:
                self._refusals.refuse(batch.worlds[at], batch.goals[at], Refusal.RESET)

    def ready(self) -> np.ndarray | bool:
        """Lockstep: (nworld,) bool, the worlds with a trajectory on every trajectory input since
        the period began (True where there is no such input)."""
        ready: np.ndarray | bool = True
        for i, counter in self.counters.items():
            ready = ready & (counter != self.seen[i])
        return ready
