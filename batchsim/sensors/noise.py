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


_S30, _S27, _S31, _S32, _S11 = (np.uint64(k) for k in (30, 27, 31, 32, 11))
_ONE = np.uint64(1)
_LOW32 = np.uint64(0xFFFFFFFF)


def _mix(x: np.ndarray) -> np.ndarray:
    """splitmix64's finalizer, in place on a uint64 array: a bijection that scrambles every bit."""
    x ^= x >> _S30
    x *= _M1
    x ^= x >> _S27
    x *= _M2
    x ^= x >> _S31
    return x


def _world_keys(seed: int, stream: np.uint64, nworld: int) -> np.ndarray:
    """(nworld,) uint64: the key of each world of a stream, before the tick is mixed in."""
    with np.errstate(over="ignore"):
        base = np.uint64(seed & 0xFFFFFFFFFFFFFFFF) ^ stream
        return _mix(_GOLDEN * (np.arange(nworld, dtype=np.uint64) + _ONE) + base)


def _element_offsets(size: int, salt: np.uint64 = _NO_SALT) -> np.ndarray:
    with np.errstate(over="ignore"):
        return _GOLDEN * (np.arange(size, dtype=np.uint64) + _ONE + salt)


def _bits(world_keys: np.ndarray, ticks: np.ndarray, elements: np.ndarray) -> np.ndarray:
    """(n, size) uint64 random bits: a hash of (world key, tick, element) for each value."""
    with np.errstate(over="ignore"):
        keys = _mix(world_keys + _GOLDEN * (ticks.astype(np.uint64) + _ONE))
        return _mix(keys[:, None] + elements)


def _normal(bits: np.ndarray) -> np.ndarray:
    """Standard normals (float32) from 64 random bits each: Box-Muller on two 32-bit halves."""
    u1 = ((bits >> _S32).astype(np.float32) + np.float32(0.5)) * np.float32(_U32)
    u2 = (bits & _LOW32).astype(np.float32) * np.float32(_U32)
    return np.sqrt(np.float32(-2.0) * np.log(u1)) * np.cos(np.float32(_TWO_PI) * u2)


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
        return (bits >> _S11).astype(np.float64) * (1.0 / 9007199254740992.0) < self._dropout

    def apply(self, values: np.ndarray, worlds: np.ndarray, ticks: np.ndarray) -> None:
        """Add the noise to `values` (n, size), or (n, ...) with `size` elements per row, in place."""
        values += self.offsets(worlds, ticks).reshape(values.shape).astype(values.dtype, copy=False)
        lost = self.dropped(worlds, ticks)
        if lost is not None:
            values[lost.reshape(values.shape)] = np.nan
