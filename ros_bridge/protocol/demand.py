"""The channel demand: which snapshot channels someone reads, so that the loop copies only
those into the snapshot (protocol/snapshot.py). Its writers (`ChannelDemand`: each worker's
row of `demand`, the channels its subscribers and goals need; a recording's `rec.want`,
protocol/recording.py; the web view's `view.want`) and its reader (the loop, `demanded`) are
both here; no rclpy.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from batchsim.memory import Memory

#: the demands beside the workers' that the loop ORs in, where the fleet has them
EXTRA = ("rec.want", "view.want")


def demand_arrays(nworker: int, nchannel: int, view: bool) -> list[tuple[str, tuple[int, ...], str]]:
    """Per worker, the channels it publishes from; with `view`, the channels the view reads."""
    arrays: list[tuple[str, tuple[int, ...], str]] = [("demand", (nworker, max(1, nchannel)), "u1")]
    if view:
        arrays.append(("view.want", (max(1, nchannel),), "u1"))
    return arrays


class ChannelDemand:
    """One reader's demand: worker `row`'s row of `demand`, or the whole of `rec.want` or
    `view.want` (`name`, row None)."""

    def __init__(self, memory: Memory, name: str = "demand", row: int | None = None):
        self.want = memory[name] if row is None else memory[name][row]

    def set(self, channels: Iterable[int]) -> None:
        """These channels and no others, written in one assignment: a channel wanted before and
        after is never seen unwanted in between."""
        want = np.zeros_like(self.want)
        want[list(channels)] = 1
        self.want[:] = want

    def add(self, channel: int) -> None:
        self.want[channel] = 1

    def clear(self) -> None:
        self.want[:] = 0


def demanded(memory: Memory) -> np.ndarray:
    """The loop: (nchannel,) bool, the channels someone reads (a worker, a recording, the view)."""
    demand = memory["demand"].any(axis=0)
    for extra in EXTRA:
        if extra in memory:
            demand = demand | memory[extra].astype(bool)
    return demand
