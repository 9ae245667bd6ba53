"""The goal refusals: an action goal the loop did not take, told to the worker that serves it.
Its writer (the physics process, `RefusalWriter`) and its reader (a worker, `RefusalReader`)
are both here, with their arrays; no rclpy.

A worker hands the loop a goal tagged with a number unique in the fleet (a FollowJointTrajectory
goal in a trajectory batch, a GripperCommand goal as a request); the controller shows the tag of
the goal it runs in its action channel. A goal the loop refuses never shows: per world, the loop
writes why (`goal.code`, a Refusal, and `goal.text`, the reason in words), then the refused
goal's tag (`goal.refused`), and the worker aborts the goal whose tag it finds there.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence

import numpy as np

from batchsim.memory import Memory
from ros_bridge.protocol.text import put_text, text_of

TEXT = 240  # bytes of a refusal's reason kept per world


class Refusal(enum.IntEnum):
    """Why the loop refused a goal (`goal.code`)."""

    INVALID = 1  # its controller refused it (the text: the controller's reason)
    RESET = 2  # its world was reset before the controller had it


#: the words of a refusal that came without its own
WORDS = {Refusal.INVALID: "refused by the controller", Refusal.RESET: "the world was reset"}


def refusal_arrays(nworld: int) -> list[tuple[str, tuple[int, ...], str]]:
    """Per world: the last goal tag the loop refused, why, and the reason in words."""
    return [("goal.refused", (nworld,), "i8"), ("goal.code", (nworld,), "i8"), ("goal.text", (nworld, TEXT), "u1")]


class RefusalWriter:
    """The physics process's side."""

    def __init__(self, memory: Memory):
        self.tag = memory["goal.refused"]
        self.code = memory["goal.code"]
        self.text = memory["goal.text"]

    def refuse(self, worlds: Sequence[int] | np.ndarray, tags: Sequence[int] | np.ndarray, code: Refusal, reasons: Sequence[str] = ()) -> None:
        """The goals `tags` of `worlds` are refused, for `code` and `reasons` (one per goal; none:
        WORDS[code]). The tag goes last, so a worker that finds it finds why."""
        for k, (world, tag) in enumerate(zip(np.asarray(worlds).tolist(), np.asarray(tags).tolist(), strict=True)):
            put_text(self.text[world], reasons[k] if reasons else WORDS[code])
            self.code[world] = int(code)
            self.tag[world] = tag


class RefusalReader:
    """A worker's side."""

    def __init__(self, memory: Memory):
        self.tag = memory["goal.refused"]
        self.code = memory["goal.code"]
        self.text = memory["goal.text"]

    def refused(self, world: int, tag: int) -> tuple[Refusal, str] | None:
        """(why, the reason) if the loop refused goal `tag` of `world`, else None."""
        if int(self.tag[world]) != tag:
            return None
        code = Refusal(int(self.code[world]))
        text = text_of(self.text[world])
        if int(self.tag[world]) != tag:  # another goal's refusal came meanwhile: its words are not ours
            text = ""
        return code, text or WORDS[code]


# --- the goals a worker holds, for the worker that follows it ---
# A worker that dies takes its accepted goals' servers with it, and their clients wait for a
# result nobody will send. Each worker notes the goal id of every world's goal in flight
# (`goal.held`, per world and action, zeros: none); a restarted worker finds them there and
# tells their clients (worker/actions.py): ABORTED on the action's status topic.


def held_arrays(nworld: int, naction: int) -> list[tuple[str, tuple[int, ...], str]]:
    return [("goal.held", (nworld, max(1, naction), 16), "u1")]


def hold(memory: Memory, world: int, action: int, goal_id: bytes) -> None:
    memory["goal.held"][world, action] = np.frombuffer(goal_id, np.uint8)


def release(memory: Memory, world: int, action: int, goal_id: bytes) -> None:
    """Forget the goal `goal_id` (a newer one held in its place stays)."""
    row = memory["goal.held"][world, action]
    if row.tobytes() == goal_id:
        row[:] = 0


def held(memory: Memory, lo: int, hi: int) -> list[tuple[int, int, bytes]]:
    """(world, action, goal id) of every goal held in worlds [lo, hi)."""
    block = memory["goal.held"][lo:hi]
    return [(lo + int(w), int(a), block[w, a].tobytes()) for w, a in zip(*np.nonzero(block.any(axis=2)), strict=True)]

