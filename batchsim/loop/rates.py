"""The loop's rates: the default control rate and the one check every rate goes through. Light
(no MuJoCo, no NumPy): ros_bridge/options.py and the command line's parser use it before any
heavy import."""

from __future__ import annotations

DEFAULT_CONTROL_RATE = 100.0  # Hz


class RateError(ValueError):
    """A rate that is not a whole fraction of the rate it is derived from.

    Attributes:
      ratio: the nearest whole number of base periods (>= 1).
      nearest: the nearest rate that would be one (base_rate / ratio).
    """

    def __init__(self, rate: float, base_rate: float, ratio: int):
        self.ratio = ratio
        self.nearest = base_rate / ratio
        super().__init__(f"{rate:g} Hz is not a whole fraction of {base_rate:g} Hz: try {self.nearest:g} Hz")

    @property
    def hint(self) -> str:
        return f"try {self.nearest:g} Hz"


def whole_ratio(base_rate: float, rate: float) -> int:
    """base_rate / rate as a whole number >= 1: the one check every rate of the loop goes
    through (control rate against the physics step, publish and sensor rates against the
    control rate, a controller YAML's update_rate). RateError when it is not whole."""
    ratio = base_rate / rate
    n = max(1, round(ratio))
    if abs(n - ratio) > 1e-6 * ratio:
        raise RateError(rate, base_rate, n)
    return n
