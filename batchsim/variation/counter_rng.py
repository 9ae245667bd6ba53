"""A counter-based random generator: every number is a hash of (seed, stream, world, counter,
element), so that world i's numbers depend on nothing but those, not on how many worlds there
are, which of them a call asks for, or in what order. Sensor noise (batchsim.sensors.noise) and
per-world randomization (batchsim.variation) both draw from it.

The hash is splitmix64's finalizer over a Weyl sequence, in numpy uint64 arithmetic
(wrapping): `bits(world_keys(seed, stream, worlds), counters, element_offsets(size))`.
"""

from __future__ import annotations

import hashlib

import numpy as np

# splitmix64 / murmur3 finalizer constants
GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S32, _S11 = (np.uint64(k) for k in (30, 27, 31, 32, 11))
_ONE = np.uint64(1)
_LOW32 = np.uint64(0xFFFFFFFF)
_NO_SALT = np.uint64(0)
_TWO_PI = 2.0 * np.pi
_U32 = 1.0 / 4294967296.0
_U53 = 1.0 / 9007199254740992.0


def stream_id(name: str) -> np.uint64:
    """A stable 64-bit id for a named stream, the same on every machine and Python."""
    return np.uint64(int.from_bytes(hashlib.blake2b(name.encode(), digest_size=8).digest(), "little"))


def mix(x: np.ndarray) -> np.ndarray:
    """splitmix64's finalizer, in place on a uint64 array: a bijection that scrambles every bit."""
    x ^= x >> _S30
    x *= _M1
    x ^= x >> _S27
    x *= _M2
    x ^= x >> _S31
    return x


def world_keys(seed: int, stream: np.uint64, worlds: np.ndarray | int) -> np.ndarray:
    """(n,) uint64: the key of each world of a stream, before the counter is mixed in.

    Args:
      worlds: (n,) world numbers, or an int n for worlds 0..n-1.
    """
    ids = (
        np.arange(worlds, dtype=np.uint64)
        if isinstance(worlds, int | np.integer)
        else np.asarray(worlds).astype(np.uint64)
    )
    with np.errstate(over="ignore"):
        base = np.uint64(seed & 0xFFFFFFFFFFFFFFFF) ^ stream
        return mix(GOLDEN * (ids + _ONE) + base)


def element_offsets(size: int, salt: np.uint64 = _NO_SALT) -> np.ndarray:
    """(size,) uint64: what each element of a draw adds to its world's key."""
    with np.errstate(over="ignore"):
        return GOLDEN * (np.arange(size, dtype=np.uint64) + _ONE + salt)


def bits(keys: np.ndarray, counters: np.ndarray, elements: np.ndarray) -> np.ndarray:
    """(n, size) uint64 random bits: a hash of (world key, counter, element) for each value.

    Args:
      keys: (n,) world keys (`world_keys`).
      counters: (n,) each world's counter (a reading's tick, a draw's number).
      elements: (size,) `element_offsets`.
    """
    with np.errstate(over="ignore"):
        k = mix(keys + GOLDEN * (np.asarray(counters).astype(np.uint64) + _ONE))
        return mix(k[:, None] + elements)


def normal32(b: np.ndarray) -> np.ndarray:
    """Standard normals (float32) from 64 random bits each: Box-Muller on two 32-bit halves."""
    u1 = ((b >> _S32).astype(np.float32) + np.float32(0.5)) * np.float32(_U32)
    u2 = (b & _LOW32).astype(np.float32) * np.float32(_U32)
    return np.sqrt(np.float32(-2.0) * np.log(u1)) * np.cos(np.float32(_TWO_PI) * u2)


def uniform64(b: np.ndarray) -> np.ndarray:
    """Uniforms in [0, 1) (float64) from the top 53 of 64 random bits each."""
    return (b >> _S11).astype(np.float64) * _U53


def normal64(b: np.ndarray) -> np.ndarray:
    """Standard normals (float64) from 64 random bits each: Box-Muller on two 32-bit halves."""
    u1 = ((b >> _S32).astype(np.float64) + 0.5) * _U32
    u2 = (b & _LOW32).astype(np.float64) * _U32
    return np.sqrt(-2.0 * np.log(u1)) * np.cos(_TWO_PI * u2)
