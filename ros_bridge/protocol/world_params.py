"""Each randomized world's draw, as text the workers put in /diagnostics. No rclpy.

The physics process writes one line per world whose draw changed (at start, and after a
reset that redraws): its seed and draw number, how to reproduce it alone, and the values that
differ from the model (batchsim.variation.report). A worker reads its worlds' lines when it
publishes /diagnostics. Writer and reader are here, beside the block's layout.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from batchsim.contract import Contract
from batchsim.memory import Memory
from batchsim.variation.report import changes
from ros_bridge.protocol.text import text_of

TEXT = 768  # bytes of a world's line, utf-8, NUL-padded (longer lines end in "...")


def param_arrays(nworld: int) -> list[tuple[str, tuple[int, ...], str]]:
    """The block: a line per world, and the draw number each line was written for."""
    return [("wp.text", (nworld, TEXT), "u1"), ("wp.draw", (nworld,), "i8")]


class ParamWriter:
    """The physics process's side: `refresh(sim)` rewrites the lines of worlds drawn anew (a
    writer of a fleet that varies nothing does nothing)."""

    def __init__(self, memory: Memory | None, world_offset: int, source: str):
        self.text = self.draw = None
        if memory is not None:
            self.text, self.draw = memory["wp.text"], memory["wp.draw"]
            self.draw[:] = -1
        self.offset = world_offset
        self.source = source

    @classmethod
    def start(cls, memory: Memory, plan: Any, sim: Contract) -> ParamWriter:
        """The writer of a fleet's plan (ros_bridge.plan.FleetPlan), every world's line written."""
        if not plan.randomized:
            return cls(None, plan.world_offset, "")
        writer = cls(memory, plan.world_offset, sim.variation.source)
        writer.refresh(sim)
        return writer

    def refresh(self, sim: Contract) -> None:
        variation = sim.variation
        if variation is None or self.draw is None:
            return
        draws = sim.draw_numbers()
        rows = np.flatnonzero(draws != self.draw)
        bound = sim.variation_bound
        if not rows.size or bound is None:
            return
        params = sim.world_params(rows)
        for k, row in enumerate(rows.tolist()):
            values = "; ".join(changes(bound, sim.model, params, k))
            line = (
                f"seed {variation.seed}, draw {draws[row]} (alone: --worlds 1 --world-offset {self.offset + row} "
                f"--randomize {self.source}): {values or 'as the model'}"
            )
            raw = line.encode()
            if len(raw) > TEXT:
                raw = raw[: TEXT - 3] + b"..."
            self.text[row] = 0
            self.text[row, : len(raw)] = np.frombuffer(raw, np.uint8)
        self.draw[rows] = draws[rows]


def read_line(memory: Memory, world: int) -> str:
    """A worker's side: world `world`'s line ("" before the physics process wrote it)."""
    return text_of(memory["wp.text"][world])
