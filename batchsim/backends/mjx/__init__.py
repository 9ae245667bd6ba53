"""The `mjx` backend: MuJoCo XLA (MJX's JAX implementation) in float32. engine.py is the engine
(MjxEngine), programs.py its jitted programs, fields.py per-world model fields.
"""

from __future__ import annotations

from batchsim.backends.mjx.engine import MjxEngine

__all__ = ["MjxEngine"]
