"""What a bridge worker does with a message that commands a world: the callbacks of its command
topics (`<ns>/commands`, `<ns>/<robot>/commands`, `<ns>/[<robot>/]actuators/<a>/command`) and of
its controllers' inputs (rows and trajectories), each checking the message and handing what
passes to the loop through shared memory (ros_bridge/protocol/commands.py; trajectories through
the request ring, trajectories.py), or rejecting it with a line (`reject`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from std_msgs.msg import Float64, Float64MultiArray

from ros_bridge.plan import FleetPlan
from ros_bridge.protocol.commands import Problem, SlotWriter, check_single, check_vector
from ros_bridge.worker.messages import parse_row, parse_trajectory
from ros_bridge.worker.trajectories import TrajectoryIntake


class CommandCallbacks:
    """The command callbacks of one worker: `commands` its command slots, `trajectories` its
    trajectory intake, `reject(world, topic, problem, reason)` and `nudge()` (lockstep: a command
    came) the worker's."""

    def __init__(
        self,
        plan: FleetPlan,
        commands: SlotWriter,
        trajectories: TrajectoryIntake,
        reject: Callable[[int, str, Problem, str], None],
        nudge: Callable[[], None],
    ):
        self.plan = plan
        self.commands = commands
        self.trajectories = trajectories
        self._reject = reject
        self._nudge = nudge

    def vector(
        self, w: int, topic: str, interfaces: list[str], owners: list[str], columns: Sequence[int] | None = None
    ) -> Callable[[Any], None]:
        """`<ns>/commands`: a value per command interface; with `columns`, one robot's
        `<ns>/<robot>/commands`: a value per interface of that robot, in its order."""
        if columns is not None:
            cols = np.array(columns, dtype=np.intp)
            interfaces, owners = [interfaces[c] for c in cols], [owners[c] for c in cols]

        def callback(msg: Float64MultiArray) -> None:
            row = np.frombuffer(msg.data, dtype=np.float64) if len(msg.data) else np.zeros(0)
            problem = check_vector(row, interfaces, owners)
            if problem is not None:
                self._reject(w, topic, *problem)
                return
            if columns is None:
                self.commands.put_row(w, row)
            else:
                self.commands.put_columns(w, cols, row)
            self._nudge()

        return callback

    def single(self, w: int, c: int, topic: str, interfaces: list[str], owners: list[str]) -> Callable[[Any], None]:
        def callback(msg: Float64) -> None:
            problem = check_single(msg.data, c, interfaces, owners)
            if problem is not None:
                self._reject(w, topic, *problem)
                return
            self.commands.put(w, c, msg.data)
            self._nudge()

        return callback

    def row(self, spec: Any, slots: SlotWriter, counter: np.ndarray, w: int, topic: str) -> Callable[[Any], None]:
        def callback(msg: Any) -> None:
            try:
                row = parse_row(spec, msg)
            except (ValueError, TypeError) as e:
                self._reject(w, topic, Problem.MALFORMED, str(e))
                return
            slots.put_row(w, row)
            self._nudge()

        return callback

    def trajectory(self, i: int, w: int, topic: str) -> Callable[[Any], None]:
        spec = self.plan.inputs[i]

        def callback(msg: Any) -> None:
            try:
                parsed = parse_trajectory(msg)
            except (ValueError, TypeError) as e:
                self._reject(w, topic, Problem.MALFORMED, str(e))
                return
            if spec.max_points and len(parsed[1]) > spec.max_points:
                self._reject(w, topic, Problem.MALFORMED, f"{len(parsed[1])} points, more than {spec.max_points}")
                return
            self.trajectories.submit(i, w, parsed)

        return callback
