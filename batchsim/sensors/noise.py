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
import hashlib
from collections.abc import Mapping
from typing import Any

import numpy as np

# splitmix64 / murmur3 finalizer constants
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_BIAS_TICK = np.uint64(0xFFFFFFFFFFFFFFFF)  # the tick a world's bias is drawn at, once
_DROPOUT_SALT = np.uint64(0x5DEECE66D)
_NO_SALT = np.uint64(0)
_TWO_PI = 2.0 * np.pi
_U32 = 1.0 / 4294967296.0

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


def stream_id(name: str) -> np.uint64:
    """A stable 64-bit id for a noise stream (a sensor's name), the same on every machine."""
    return np.uint64(int.from_bytes(hashlib.blake2b(name.encode(), digest_size=8).digest(), "little"))


def _mix(x: np.ndarray) -> np.ndarray:
    """splitmix64's finalizer, in place on a uint64 array: a bijection that scrambles every bit."""
    x ^= x >> np.uint64(30)
    x *= _M1
    x ^= x >> np.uint64(27)
    x *= _M2
    x ^= x >> np.uint64(31)
    return x


def _keys(seed: int, stream: np.uint64, worlds: np.ndarray, ticks: np.ndarray) -> np.ndarray:
    """(n, 1) uint64 keys of (seed, stream, world, tick) for the n worlds of a call."""
    with np.errstate(over="ignore"):
        key = np.full(len(worlds), np.uint64(seed & 0xFFFFFFFFFFFFFFFF) ^ stream, np.uint64)
        key = _mix(key + _GOLDEN * (worlds.astype(np.uint64) + np.uint64(1)))
        key = _mix(key + _GOLDEN * (ticks.astype(np.uint64) + np.uint64(1)))
    return key[:, None]


def _bits(keys: np.ndarray, size: int, salt: np.uint64 = _NO_SALT) -> np.ndarray:
    """(n, size) uint64 random bits, one hash per (key, element)."""
    with np.errstate(over="ignore"):
        x = keys + _GOLDEN * (np.arange(size, dtype=np.uint64) + np.uint64(1) + salt)
        return _mix(x)


def _normal(bits: np.ndarray) -> np.ndarray:
    """Standard normals (float32) from 64 random bits each: Box-Muller on two 32-bit halves."""
    u1 = ((bits >> np.uint64(32)).astype(np.float32) + np.float32(0.5)) * np.float32(_U32)
    u2 = (bits & np.uint64(0xFFFFFFFF)).astype(np.float32) * np.float32(_U32)
    return np.sqrt(np.float32(-2.0) * np.log(u1)) * np.cos(np.float32(_TWO_PI) * u2)


class NoiseStream:
    """The noise of one sensor (or one group of state columns) across worlds and readings.

    Args:
      noise: the parameters.
      seed: the run's seed.
      name: the stream's name (the sensor's); two streams of one seed are independent.
      size: values per world and reading (the sensor's dimension, pixels, rays).
    """

    def __init__(self, noise: Noise, seed: int, name: str, size: int):
        self.noise = noise
        self.seed = int(seed)
        self.name = name
        self.size = int(size)
        self._stream = stream_id(name)
        self._bias: dict[int, np.ndarray] = {}

    def offsets(self, worlds: np.ndarray, ticks: np.ndarray) -> np.ndarray:
        """(n, size) float32: what the noise adds to each value of the n worlds at their ticks.

        Args:
          worlds: (n,) world indices.
          ticks: (n,) each world's reading counter.
        """
        nz = self.noise
        out = np.full((len(worlds), self.size), nz.mean, np.float32)
        if nz.stddev:
            out += np.float32(nz.stddev) * _normal(_bits(_keys(self.seed, self._stream, worlds, ticks), self.size))
        if nz.bias_mean or nz.bias_stddev:
            out += self.bias(worlds)
        return out

    def bias(self, worlds: np.ndarray) -> np.ndarray:
        """(n, size) float32: each world's bias, drawn once per world and fixed for the run."""
        nz = self.noise
        ticks = np.full(len(worlds), _BIAS_TICK, np.uint64)
        keys = _keys(self.seed, self._stream ^ np.uint64(0xB1A5), worlds, ticks)
        return np.float32(nz.bias_mean) + np.float32(nz.bias_stddev) * _normal(_bits(keys, self.size))

    def dropped(self, worlds: np.ndarray, ticks: np.ndarray) -> np.ndarray | None:
        """(n, size) bool: the values lost at this reading, or None without dropout."""
        if not self.noise.dropout:
            return None
        keys = _keys(self.seed, self._stream, worlds, ticks)
        u = (_bits(keys, self.size, _DROPOUT_SALT) >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)
        return u < self.noise.dropout

    def apply(self, values: np.ndarray, worlds: np.ndarray, ticks: np.ndarray) -> None:
        """Add the noise to `values` (n, size), or (n, ...) with `size` elements per row, in place."""
        values += self.offsets(worlds, ticks).reshape(values.shape).astype(values.dtype, copy=False)
        lost = self.dropped(worlds, ticks)
        if lost is not None:
            values[lost.reshape(values.shape)] = np.nan
