"""Commands between the ROS side and the loop, through shared memory. No rclpy here.

A bridge worker (ROS callbacks) checks each message (`check_vector`, `check_single`) and
writes what passes into per-world slots with `CommandWriter`: the values, then a counter
per slot that only the worker increments. The loop takes them with `CommandReader` once per
control period: a slot whose counter moved since the last period holds a new command. So a
flood of messages costs the loop one comparison per period, a slow or dead worker never
stalls it, and a restarted worker that continues the counters never replays old commands.

Rejections are counted per world with the topic and reason of the last (`RejectionWriter`:
a worker's in `rej`, the loop's controllers' in `hrej`), for BAD_COMMAND and /diagnostics.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence

import numpy as np

from batchsim.memory import Memory
from batchsim.types import MAX_COMMAND
from ros_bridge.protocol.text import put_text, text_of

TEXT = 240  # bytes of the last rejection's line ("<topic>: <reason>") kept per world
TOPIC = 240  # bytes of the last rejection's topic kept per world


class Problem(enum.Enum):
    """Why a command was rejected: with the topic, the key of the log throttle."""

    LENGTH = "length"
    NOT_FINITE = "not_finite"
    RANGE = "range"
    CLAIMED = "claimed"
    UNKNOWN_ACTUATOR = "unknown_actuator"
    MALFORMED = "malformed"  # a controller input that does not parse
    INVALID = "invalid"  # a controller input its controller refused
    BACKLOG = "backlog"  # the loop is too far behind to take more
    FLOOD = "flood"  # more messages on one world's topic than the worker takes (ros_bridge/worker/intake.py)


def check_vector(row: np.ndarray, interfaces: Sequence[str], owners: Sequence[str]) -> tuple[Problem, str] | None:
    """A whole command row for one world (`<ns>/commands`): None if it may be applied.

    Args:
      row: the message's values.
      interfaces: command interface names, in column order.
      owners: per column, the controller that claimed it, or "".
    """
    n = len(interfaces)
    if row.shape != (n,):
        return Problem.LENGTH, f"{row.size} values, expected {n} (one per command interface: {', '.join(interfaces)})"
    finite = np.isfinite(row)
    if not finite.all():
        bad = int(np.flatnonzero(~finite)[0])
        return Problem.NOT_FINITE, f"value {row[bad]} for {interfaces[bad]} is not finite"
    big = np.abs(row) >= MAX_COMMAND
    if big.any():
        bad = int(np.flatnonzero(big)[0])
        return Problem.RANGE, f"value {row[bad]:g} for {interfaces[bad]} is beyond {MAX_COMMAND:g}"
    claimed = sorted({o for o in owners if o})
    if claimed:
        return Problem.CLAIMED, "interfaces are claimed by controller " + ", ".join(repr(o) for o in claimed)
    return None


def check_single(value: float, column: int, interfaces: Sequence[str], owners: Sequence[str]) -> tuple[Problem, str] | None:
    """One interface's command (`<ns>/actuators/<a>/command`): None if it may be applied."""
    if not math.isfinite(value):
        return Problem.NOT_FINITE, f"value {value} is not finite"
    if abs(value) >= MAX_COMMAND:
        return Problem.RANGE, f"value {value:g} is beyond {MAX_COMMAND:g}"
    if owners[column]:
        return Problem.CLAIMED, f"{interfaces[column]} is claimed by controller {owners[column]!r}"
    return None


def slot_arrays(name: str, nworld: int, width: int, per_column: bool) -> list[tuple[str, tuple[int, ...], str]]:
    """Layout entries of one block of command slots: values and counters (one per world and
    column, or one per world)."""
    counters = (nworld, width) if per_column else (nworld,)
    return [(f"{name}.value", (nworld, width), "f8"), (f"{name}.seq", counters, "i8")]


class SlotWriter:
    """The worker's side of a block of slots: write values, then move their counters."""

    def __init__(self, memory: Memory, name: str):
        self.value = memory[f"{name}.value"]
        self.seq = memory[f"{name}.seq"]

    def put_row(self, world: int, row: np.ndarray) -> None:
        self.value[world] = row
        self.seq[world] += 1

    def put(self, world: int, column: int, value: float) -> None:
        self.value[world, column] = value
        self.seq[world, column] += 1

    def put_columns(self, world: int, columns: np.ndarray, values: np.ndarray) -> None:
        """Some columns of a world's row (one robot's of a world of several, `<ns>/<robot>/commands`)."""
        self.value[world, columns] = values
        self.seq[world, columns] += 1


class SlotReader:
    """The loop's side: what arrived since the last `take`.

    Args:
      memory: the shared arrays.
      name: the block's name.
    """

    def __init__(self, memory: Memory, name: str):
        self.value = memory[f"{name}.value"]
        self.seq = memory[f"{name}.seq"]
        self.seen = self.seq.copy()

    def fresh(self) -> np.ndarray:
        """Slots with something not taken yet: the shape of the counters, bool."""
        return self.seq != self.seen

    def take(self) -> tuple[np.ndarray, np.ndarray]:
        """(new, values): `new` marks the slots written since the last take (counter shape,
        bool); `values` is the value block, read after the counters, so every marked slot
        holds at least the command its counter announced."""
        now = self.seq.copy()
        new = now != self.seen
        self.seen = now
        return new, self.value

    def drop(self, worlds: np.ndarray | None, columns: np.ndarray | None = None) -> None:
        """Forget what arrived for all or the listed worlds (they were reset); with `columns`,
        in those columns only (one robot of the worlds was reset)."""
        if worlds is None:
            self.seen = self.seq.copy()
        elif columns is None:
            self.seen[worlds] = self.seq[worlds]
        else:
            at = np.ix_(np.asarray(worlds), np.asarray(columns))
            self.seen[at] = self.seq[at]


def rejection_arrays(name: str, nworld: int) -> list[tuple[str, tuple[int, ...], str]]:
    """Layout entries of one writer's rejections: count, period of the last, its line and topic."""
    return [
        (f"{name}.count", (nworld,), "i8"),
        (f"{name}.period", (nworld,), "i8"),
        (f"{name}.text", (nworld, TEXT), "u1"),
        (f"{name}.topic", (nworld, TOPIC), "u1"),
    ]


class RejectionWriter:
    """Per-world rejection counters and the last rejection, written by one side only (and read
    by the others: `reason`, `topic`)."""

    def __init__(self, memory: Memory, name: str):
        self.count = memory[f"{name}.count"]
        self.period = memory[f"{name}.period"]
        self.text = memory[f"{name}.text"]
        self.topics = memory[f"{name}.topic"]

    def put(self, world: int, period: int, topic: str, reason: str, count: int = 1) -> None:
        """`count` messages for `world` on `topic` were rejected, the last for `reason`."""
        put_text(self.topics[world, :-1], topic)  # a NUL left at the end
        put_text(self.text[world, :-1], f"{topic}: {reason}")
        self.period[world] = period
        self.count[world] += count

    def reason(self, world: int) -> str:
        """The last rejection, as the log and /diagnostics say it: "<topic>: <reason>"."""
        return text_of(self.text[world])

    def topic(self, world: int) -> str:
        """The topic of the last rejection."""
        return text_of(self.topics[world])


def bad_commands(mine: RejectionWriter, host: RejectionWriter, world: int) -> tuple[int, str]:
    """A world's rejected commands in all, the bridge workers' (`mine`, block `rej`) and the
    loop's controllers' (`host`, block `hrej`), and the last one's "<topic>: <reason>" ("" with none):
    what /diagnostics says live (worker/diagnostics.py) and a recording's /diagnostics records."""
    count = int(mine.count[world]) + int(host.count[world])
    if not count:
        return 0, ""
    return count, host.reason(world) if host.period[world] > mine.period[world] else mine.reason(world)

