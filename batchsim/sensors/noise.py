"""Sensor noise: Gaussian noise, a per-world bias and dropout, seeded per world.

Every random number is a hash of (seed, stream, world, tick, element), a counter-based
generator: world 3's noise at its 10th reading is the same whatever the other worlds do,
how many worlds there are, or which subset of worlds a call reads. Runs with the same seed
repeat exactly; a reset world goes on with new noise (its tick keeps counting).

The model is Gazebo's sensor noise, per value:

    reading = truth + mean + bias[world] + stddev * N(0, 1)      bias[world] ~ N(bias_mean, bias_stddev)

and, for depth pixels and lidar ranges, with probability `dropout` the value is lost: NaN,
REP 117's "erroneous measurement".
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from batchsim.variation.counter_rng import bits as _bits
from batchsim.variation.counter_rng import element_offsets as _element_offsets
from batchsim.variation.counter_rng import normal32 as _normal
from batchsim.variation.counter_rng import stream_id as stream_id
from batchsim.variation.counter_rng import uniform64
from batchsim.variation.counter_rng import world_keys as _world_keys

_BIAS_TICK = np.uint64(0xFFFFFFFFFFFFFFFF)  # the tick a world's bias is drawn at, once
_DROPOUT_SALT = np.uint64(0x5DEECE66D)

NOISE_KEYS = ("mean", "stddev", "bias_mean", "bias_stddev", "dropout")


@dataclasses.dataclass(frozen=True)
class Noise:
    """One sensor's noise parameters, in the sensor's units (rad, m, N, m/s^2, ...).

    Attributes:
      mean: constant offset added to every value.
      stddev: standard deviation of the white noise drawn per value and reading.
      bias_mean, bias_stddev: each world's bias is drawn once from N(bias_mean, bias_stddev).
      dropout: probability that a depth pixel or lidar range is lost (NaN); 0 elsewhere.
    """

    mean: float = 0.0
    stddev: float = 0.0
    bias_mean: float = 0.0
    bias_stddev: float = 0.0
    dropout: float = 0.0

    @classmethod
    def parse(cls, value: Any, where: str) -> Noise:
        """From a YAML mapping; ValueError naming `where` and the key at fault."""
        if not isinstance(value, Mapping):
            raise ValueError(f"{where}: noise must be a mapping of {', '.join(NOISE_KEYS)}, got {value!r}")
        unknown = sorted(set(value) - set(NOISE_KEYS))
        if unknown:
            raise ValueError(f"{where}: unknown noise key {unknown[0]!r} (known: {', '.join(NOISE_KEYS)})")
        fields: dict[str, float] = {}
        for key, raw in value.items():
            try:
                number = float(raw)
            except (TypeError, ValueError):
                raise ValueError(f"{where}.{key}: must be a number, got {raw!r}") from None
            if not np.isfinite(number):
                raise ValueError(f"{where}.{key}: must be finite, got {raw!r}")
            if key in ("stddev", "bias_stddev") and number < 0:
                raise ValueError(f"{where}.{key}: must be >= 0, got {number:g}")
            if key == "dropout" and not 0.0 <= number <= 1.0:
                raise ValueError(f"{where}.dropout: a probability in [0, 1], got {number:g}")
            fields[key] = number
        return cls(**fields)

    @property
    def active(self) -> bool:
        return any((self.mean, self.stddev, self.bias_mean, self.bias_stddev, self.dropout))


class NoiseStream:
    """The noise of one sensor (or of a set of state columns) across worlds and readings.

    Args:
      noise: the parameters, or one Noise per value (`size` of them).
      seed: the run's seed.
      name: the stream's name (the sensor's); two streams of one seed are independent.
      size: values per world and reading (the sensor's dimension, pixels, rays).
    """

    def __init__(self, noise: Noise | list[Noise], seed: int, name: str, size: int):
        per_value = noise if isinstance(noise, list) else [noise]
        self.noise = per_value[0] if len(per_value) == 1 else per_value
        self.seed = int(seed)
        self.name = name
        self.size = int(size)
        self._stream = stream_id(name)

        def column(key: str) -> np.float32 | np.ndarray:
            values = np.array([getattr(n, key) for n in per_value], np.float32)
            return values[0] if len(per_value) == 1 else values

        self._mean, self._stddev = column("mean"), column("stddev")
        self._bias_mean, self._bias_stddev = column("bias_mean"), column("bias_stddev")
        self._dropout = max(n.dropout for n in per_value)
        self._has_bias = any(n.bias_mean or n.bias_stddev for n in per_value)
        self._has_stddev = any(n.stddev for n in per_value)
        self._bias: np.ndarray | None = None  # every world's, once asked for
        self._keys = np.zeros(0, np.uint64)  # every world's key, grown as worlds are asked for
        self._elements = _element_offsets(self.size)
        self._dropout_elements = _element_offsets(self.size, _DROPOUT_SALT)

    def _world_keys(self, worlds: np.ndarray) -> np.ndarray:
        top = int(worlds.max()) + 1 if len(worlds) else 0
        if len(self._keys) < top:
            self._keys = _world_keys(self.seed, self._stream, top)
        return self._keys[worlds]

    def offsets(self, worlds: np.ndarray, ticks: np.ndarray) -> np.ndarray:
        """(n, size) float32: what the noise adds to each value of the n worlds at their ticks.

        Args:
          worlds: (n,) world indices.
          ticks: (n,) each world's reading counter.
        """
        out = np.empty((len(worlds), self.size), np.float32)
        out[:] = self._mean
        if self._has_stddev:
            out += self._stddev * _normal(_bits(self._world_keys(worlds), ticks, self._elements))
        if self._has_bias:
            out += self.bias(worlds)
        return out

    def bias(self, worlds: np.ndarray) -> np.ndarray:
        """(n, size) float32: each world's bias, drawn once per world and fixed for the run."""
        top = int(worlds.max()) + 1 if len(worlds) else 0
        if self._bias is None or len(self._bias) < top:
            keys = _world_keys(self.seed, self._stream ^ np.uint64(0xB1A5), top)
            ticks = np.full(top, _BIAS_TICK, np.uint64)
            self._bias = self._bias_mean + self._bias_stddev * _normal(_bits(keys, ticks, self._elements))
        return self._bias[worlds]

    def dropped(self, worlds: np.ndarray, ticks: np.ndarray) -> np.ndarray | None:
        """(n, size) bool: the values lost at this reading, or None without dropout."""
        if not self._dropout:
            return None
        bits = _bits(self._world_keys(worlds), ticks, self._dropout_elements)
        return uniform64(bits) < self._dropout

    def apply(self, values: np.ndarray, worlds: np.ndarray, ticks: np.ndarray) -> None:
        """Add the noise to `values` (n, size), or (n, ...) with `size` elements per row, in place."""
        values += self.offsets(worlds, ticks).reshape(values.shape).astype(values.dtype, copy=False)
        lost = self.dropped(worlds, ticks)
        if lost is not None:
            values[lost.reshape(values.shape)] = np.nan
