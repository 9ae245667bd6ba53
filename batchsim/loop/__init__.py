"""The simulation loop and what runs beside it: sim_loop.py (SimLoop, controller_manager's loop
batched over worlds: read, participants, write, step, paced to a real-time factor),
realtime.py (the loop thread's scheduling and cores), sampler.py (the participant that renders
cameras and casts lidars when they are due).
"""

from __future__ import annotations

from batchsim.loop.sim_loop import (
    DEFAULT_CONTROL_RATE,
    LoopStats,
    Participant,
    RateError,
    SimLoop,
    format_stats,
    whole_ratio,
)
from batchsim.types import OptionError

__all__ = [
    "DEFAULT_CONTROL_RATE",
    "LoopStats",
    "OptionError",
    "Participant",
    "RateError",
    "SimLoop",
    "format_stats",
    "whole_ratio",
]
