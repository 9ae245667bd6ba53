"""The spline math of the trajectory controller: segment polynomials and their sampling.

A segment is a polynomial in s, the time since the point it leaves: six (njoint,)
coefficients of s^0 .. s^5 (held coefficient first: (6, n, njoint) for n segments, so that
making a batch of them is one matrix product), made from the points at its two ends (ros2_control's
Trajectory Representation): linear between points that give positions only, cubic
Hermite where they give velocities too, quintic where they give accelerations as well.
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


HELD = 0  # interpolation none: each point held until the next one's time (a `coefficients` kind)
ENDS = ("p0", "p1", "v0", "v1", "a0", "a1")  # the end values of a segment, as `coefficients` takes them

# Each kind's coefficients: c_k = sum of w * x / T^m over its terms (x, m, w), h = p1 - p0.
# m is always k less 0, 1 or 2 for a position, velocity or acceleration (the units of c_k).
_TERMS: dict[int, dict[int, tuple[tuple[str, int, float], ...]]] = {
    HELD: {0: (("p0", 0, 1.0),), 1: (("v0", 0, 1.0),), 2: (("a0", 0, 0.5),)},  # the point as it is
    LINEAR: {0: (("p0", 0, 1.0),), 1: (("h", 1, 1.0),)},
    CUBIC: {  # Hermite
        0: (("p0", 0, 1.0),),
        1: (("v0", 0, 1.0),),
        2: (("h", 2, 3.0), ("v0", 1, -2.0), ("v1", 1, -1.0)),
        3: (("h", 3, -2.0), ("v0", 2, 1.0), ("v1", 2, 1.0)),
    },
    QUINTIC: {
        0: (("p0", 0, 1.0),),
        1: (("v0", 0, 1.0),),
        2: (("a0", 0, 0.5),),
        3: (("h", 3, 10.0), ("v0", 2, -6.0), ("a0", 1, -1.5), ("v1", 2, -4.0), ("a1", 1, 0.5)),
        4: (("h", 4, -15.0), ("v0", 3, 8.0), ("a0", 2, 1.5), ("v1", 3, 7.0), ("a1", 2, -1.0)),
        5: (("h", 5, 6.0), ("v0", 4, -3.0), ("a0", 3, -0.5), ("v1", 4, -3.0), ("a1", 3, 0.5)),
    },
}


def _tables() -> tuple[np.ndarray, np.ndarray]:
    """From _TERMS, per kind: (4, 6, 6) the matrix that makes T^k c_k from the end values in
    units of a position (p0, p1, v0 T, v1 T, a0 T^2, a1 T^2), and (4, 6) bool the ends it reads."""
    matrix = np.zeros((4, 6, 6))
    for kind, coefficient in _TERMS.items():
        for k, terms in coefficient.items():
            for x, m, w in terms:
                for end, sign in ((("p1", 1.0), ("p0", -1.0)) if x == "h" else ((x, 1.0),)):
                    j = ENDS.index(end)
                    assert m == k - j // 2  # x / T^m = (x T^(j // 2)) / T^k
                    matrix[kind, k, j] += sign * w
    return matrix, (matrix != 0).any(axis=1)


_MATRIX, _READS = _tables()
_COLUMNS = [np.flatnonzero(reads) for reads in _READS]  # the ends each kind reads
# the derivatives of s^k: row r (position, velocity, acceleration) of evaluate's basis is
# _DERIVATIVE[r, k] * s^(k - r), taken from column _DERIVATIVE_COLUMN[r, k] of _powers(s)
_DERIVATIVE = np.array([[1.0] * 6, [0, 1, 2, 3, 4, 5], [0, 0, 2, 6, 12, 20]])
_DERIVATIVE_COLUMN = np.array([[1 + k - r if k >= r else 0 for k in range(6)] for r in range(3)]).reshape(-1)
_HOLD = np.array([1.0, 0, 0, 0, 0, 0] + [0] * 12)  # past the last point: p = c0, at rest


def spline_of(has_velocities: np.ndarray, has_accelerations: np.ndarray) -> np.ndarray:
    """(n,) int8 Spline of each trajectory, from which fields its points give."""
    return np.where(has_accelerations, QUINTIC, np.where(has_velocities, CUBIC, LINEAR)).astype(np.int8)


def _kinds(kind: np.ndarray) -> np.ndarray:
    """The distinct kinds of (n,) Spline or HELD (the usual one kind without a sort)."""
    return kind[:1] if len(kind) and (kind == kind[0]).all() else np.unique(kind)


def planes_read(kind: np.ndarray) -> np.ndarray:
    """(3,) bool: whether segments of these kinds ((n,) Spline or HELD) read the position,
    velocity, acceleration of their points."""
    return _READS[_kinds(kind)].reshape(-1, 3, 2).any(axis=(0, 2))


def _powers(x: np.ndarray) -> np.ndarray:
    """(n, 7): 0, then x^0 .. x^5 of each of the (n,) x."""
    out = np.zeros((len(x), 7))
    out[:, 1] = 1.0
    out[:, 2] = x
    for m in range(3, 7):
        np.multiply(out[:, m - 1], x, out=out[:, m])
    return out


def coefficients(
    kind: np.ndarray, ends: np.ndarray, T: np.ndarray, out: np.ndarray | None = None
) -> np.ndarray:
    """(6, n, njoint): segment polynomials, the coefficients of s^0 .. s^5.

    Args:
      kind: (n,) Spline of each segment (linear from positions only, cubic Hermite from
        positions and velocities, quintic from all three), or HELD: the point's own p, v
        and a / 2 (evaluated at s = 0, they give the point as it is; pass T = 1).
      ends: (6, n, njoint) C-contiguous, the values at the segment's two ends, in ENDS order
        (p0, p1, v0, v1, a0, a1): overwritten (those its kind does not read may be anything).
      T: (n,) the segment's length; one <= 0 (a last point's) is taken as 1.
      out: (6, n, njoint) C-contiguous, where to write them, or None.
    """
    kinds = _kinds(kind)
    T = np.where(T > 0, T, 1.0)
    reads = _READS[kinds].any(axis=0)
    if reads[2]:  # each value in units of a position: v T, a T^2 (exact for T = 1)
        ends[2:4] *= T[:, None]
    if reads[4]:
        ends[4:6] *= (T * T)[:, None]
    if out is None:
        out = np.empty_like(ends)
    if len(kinds) == 1:  # the usual case: one kind, one matrix product for every segment
        _product(int(kinds[0]), ends, out)
    else:
        for k in kinds.tolist():
            of = np.flatnonzero(kind == k)
            out[:, of] = _product(k, np.ascontiguousarray(ends[:, of]), np.empty((6, len(of), ends.shape[2])))
    out *= _powers(1.0 / T)[:, 1:].T[:, :, None]
    return out


def _product(kind: int, ends: np.ndarray, out: np.ndarray) -> np.ndarray:
    """T^k c_k into `out` (6, n, njoint), C-contiguous: the kind's matrix times the ends it reads
    (a prefix of ENDS but for HELD's), the others not read."""
    columns = _COLUMNS[kind]
    m = len(columns)
    x = ends[:m] if columns[-1] == m - 1 else ends[columns]
    np.matmul(_MATRIX[kind][:, columns], x.reshape(m, -1), out=out.reshape(6, -1))
    return out


def evaluate(polynomials: np.ndarray, s: np.ndarray, done: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """(3, n, njoint): position, velocity and acceleration of each polynomial at its `s`.

    Args:
      polynomials: (6, n, njoint) coefficients of s^0 .. s^5.
      s: (n,) time since the segment's point (clamped at 0; 0 for a HELD point).
      done: (n,) past the last point: the point's position, at rest.
      out: (3, n, njoint) where to write them, or None.
    """
    # position, velocity and acceleration as one product: (n, 3, 6) derivatives of s^k @ (n, 6, nj)
    basis = _powers(np.maximum(s, 0.0))[:, _DERIVATIVE_COLUMN] * _DERIVATIVE.reshape(-1)
    basis[done] = _HOLD
    if out is None:
        out = np.empty((3, len(s), polynomials.shape[2]))
    np.matmul(basis.reshape(len(s), 3, 6), polynomials.transpose(1, 0, 2), out=out.transpose(1, 0, 2))
    return out
