"""The spline math of the trajectory controller: segment polynomials and their sampling.

A segment is a polynomial in s, the time since the point it leaves, stored as six
(njoint,) coefficients of s^0 .. s^5 (ros2_control's Trajectory Representation): linear
between points that give positions only, cubic Hermite where they give velocities too,
quintic where they give accelerations as well.
"""

from __future__ import annotations

import enum

import numpy as np


class Spline(enum.IntEnum):
    """How a trajectory's segments interpolate, from what its points give."""

    LINEAR = 1  # positions only
    CUBIC = 2  # and velocities
    QUINTIC = 3  # and accelerations


LINEAR, CUBIC, QUINTIC = (int(s) for s in Spline)  # as stored in int8 arrays


class Interpolation(enum.Enum):
    """The `interpolation_method` parameter."""

    SPLINES = "splines"
    NONE = "none"


_D1 = np.arange(1.0, 6.0)  # d/ds s^k = k s^(k-1), k = 1..5
_D2 = np.array([2.0, 6.0, 12.0, 20.0])  # d2/ds2 s^k = k (k-1) s^(k-2), k = 2..5
_HOLD = np.array([[1.0, 0, 0, 0, 0, 0], [0] * 6, [0] * 6])  # past the last point: p = c0, at rest


def spline_of(has_velocities: np.ndarray, has_accelerations: np.ndarray) -> np.ndarray:
    """(n,) int8 Spline of each trajectory, from which fields its points give."""
    return np.where(has_accelerations, QUINTIC, np.where(has_velocities, CUBIC, LINEAR)).astype(np.int8)


def coefficients(
    spline: np.ndarray,
    p0: np.ndarray,
    p1: np.ndarray,
    v0: np.ndarray,
    v1: np.ndarray,
    a0: np.ndarray,
    a1: np.ndarray,
    T: np.ndarray,
) -> tuple[np.ndarray, ...]:
    """Segment polynomials: the six (n, njoint) coefficients of s^0 .. s^5.

    Args:
      spline: (n,) Spline of each segment: linear from positions only, cubic Hermite from
        positions and velocities, quintic from all three.
      p0, p1, v0, v1, a0, a1: (n, njoint) the values at the segment's two ends.
      T: (n, 1) its length, > 0.
    """
    kinds = spline[:1] if len(spline) and (spline == spline[0]).all() else np.unique(spline)
    if len(kinds) > 1:
        out = [np.zeros(p0.shape) for _ in range(6)]
        for kind in kinds:
            m = spline == kind
            part = coefficients(spline[m], p0[m], p1[m], v0[m], v1[m], a0[m], a1[m], T[m])
            for o, c in zip(out, part, strict=True):
                o[m] = c
        return tuple(out)
    h = p1 - p0
    zero = np.broadcast_to(0.0, h.shape)  # a read-only view: no array to fill
    if len(kinds) == 0 or kinds[0] == LINEAR:
        return p0, h / T, zero, zero, zero, zero
    if kinds[0] == CUBIC:
        inverse = 1.0 / T
        c2 = (3 * h * inverse - (2 * v0 + v1)) * inverse
        c3 = ((v0 + v1) - 2 * h * inverse) * inverse * inverse
        return p0, v0, c2, c3, zero, zero
    T2 = T * T
    T3 = T2 * T
    b3 = (20 * h - (8 * v1 + 12 * v0) * T - (3 * a0 - a1) * T2) / (2 * T3)
    b4 = (-30 * h + (14 * v1 + 16 * v0) * T + (3 * a0 - 2 * a1) * T2) / (2 * T3 * T)
    b5 = (12 * h - 6 * (v1 + v0) * T + (a1 - a0) * T2) / (2 * T3 * T2)
    return p0, v0, a0 / 2, b3, b4, b5


def point_rows(
    steps: np.ndarray,
    offsets: np.ndarray,
    owner: np.ndarray,
    spline: np.ndarray,
    points: tuple[np.ndarray, ...],
    step_points: bool,
) -> np.ndarray:
    """(npoint, 6, njoint): each point's pool row, the polynomial of the segment to the next
    point (the last point's, and every point's with interpolation none: its p, v, a / 2).

    Args:
      steps: (npoint - 1,) the time from each point to the next one of the flat arrays.
      offsets: (n + 1,) the first point of each trajectory (CSR, as TrajectoryBatch.offsets).
      owner: (npoint,) the trajectory of each point.
      spline: (n,) Spline of each trajectory.
      points: (p, v, a), each (npoint, njoint).
      step_points: interpolation none: hold each point until the next one's time.
    """
    p, v, a = points
    npoint, nj = p.shape
    rows = np.empty((npoint, 6, nj))
    if step_points or npoint < 2:
        held = np.arange(npoint)
    else:
        # every point to the next, across trajectories too (those rows are overwritten below)
        T = steps[:, None]
        with np.errstate(all="ignore"):
            c = coefficients(spline[owner[:-1]], p[:-1], p[1:], v[:-1], v[1:], a[:-1], a[1:], T)
        for k in range(6):
            rows[:-1, k] = c[k]
        held = offsets[1:][offsets[1:] > offsets[:-1]] - 1  # each trajectory's last point
    rows[held, 0], rows[held, 1], rows[held, 2] = p[held], v[held], 0.5 * a[held]
    rows[held, 3:] = 0.0
    return rows


def evaluate(polynomials: np.ndarray, s: np.ndarray, done: np.ndarray, step_points: bool) -> np.ndarray:
    """(n, 3, njoint): position, velocity and acceleration of each polynomial at its `s`.

    Args:
      polynomials: (n, 6, njoint) coefficients of s^0 .. s^5.
      s: (n,) time since the segment's point (clamped at 0).
      done: (n,) past the last point: the point's position, at rest.
      step_points: interpolation none: the point's own p, v, a (rows store a / 2).
    """
    # position, velocity and acceleration as one product: (n, 3, 6) derivatives of s^k @ (n, 6, nj)
    n = len(s)
    basis = np.zeros((n, 3, 6))
    if step_points:
        basis[:, 0, 0], basis[:, 1, 1], basis[:, 2, 2] = 1.0, 1.0, 2.0
    else:
        powers = np.ones((n, 6))
        powers[:, 1:] = np.maximum(s, 0.0)[:, None]
        np.cumprod(powers, axis=1, out=powers)
        basis[:, 0] = powers
        basis[:, 1, 1:] = powers[:, :5] * _D1
        basis[:, 2, 2:] = powers[:, :4] * _D2
    basis[done] = _HOLD
    return basis @ polynomials
