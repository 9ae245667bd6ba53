"""The simulation loop and what runs beside it: sim_loop.py (SimLoop, controller_manager's loop
batched over worlds: read, participants, write, step, paced to a real-time factor),
realtime.py (the loop thread's scheduling and cores), sampler.py (the participant that renders
cameras and casts lidars when they are due).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

# imported on first use (PEP 562): `batchsim.loop.realtime` and `.rates` come without the loop's
# MuJoCo and NumPy imports (the command line parses its flags with them)
_LAZY = {
    "DEFAULT_CONTROL_RATE": "batchsim.loop.rates",
    "LoopStats": "batchsim.loop.sim_loop",
    "OptionError": "batchsim.types",
    "Participant": "batchsim.loop.sim_loop",
    "RateError": "batchsim.loop.rates",
    "SimLoop": "batchsim.loop.sim_loop",
    "format_stats": "batchsim.loop.sim_loop",
    "whole_ratio": "batchsim.loop.rates",
}

if TYPE_CHECKING:
    from batchsim.loop.rates import DEFAULT_CONTROL_RATE, RateError, whole_ratio
    from batchsim.loop.sim_loop import LoopStats, Participant, SimLoop, format_stats
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


def __getattr__(name: str) -> Any:
    if name not in _LAZY:
        raise AttributeError(f"module 'batchsim.loop' has no attribute {name!r}")
    value = getattr(importlib.import_module(_LAZY[name]), name)
    globals()[name] = value
    return value
