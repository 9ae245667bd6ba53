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
# the coefficients each kind makes (those after are 0): the held point's c0..c2, a line's c0, c1, ...
TERMS = np.array([int(np.flatnonzero((m != 0).any(axis=1)).max()) + 1 for m in _MATRIX])
CUBIC_TERMS = int(TERMS[CUBIC])  # every kind but QUINTIC makes at most this many


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
    m = int(TERMS[kinds].max())
    scale = np.empty((m, len(T)))  # 1 / T^k, contiguous per k
    scale[0] = 1.0
    np.divide(1.0, T, out=scale[1])
    for k in range(2, m):
        np.multiply(scale[k - 1], scale[1], out=scale[k])
    out[1:m] *= scale[1:, :, None]  # c_k = (T^k c_k) / T^k
    return out


def _product(kind: int, ends: np.ndarray, out: np.ndarray) -> np.ndarray:
    """T^k c_k into `out` (6, n, njoint), C-contiguous: the kind's matrix times the ends it reads
    (a prefix of ENDS but for HELD's), the others not read; the coefficients it does not make, 0.
    One matrix product (BLAS): on the GPU hosts a tenth of the time of a term-by-term sum."""
    columns, m = _COLUMNS[kind], int(TERMS[kind])
    x = ends[: len(columns)] if columns[-1] == len(columns) - 1 else ends[columns]
    np.matmul(_MATRIX[kind][:m, columns], x.reshape(len(columns), -1), out=out[:m].reshape(m, -1))
    out[m:] = 0.0
    return out


def evaluate(
    polynomials: np.ndarray, s: np.ndarray, done: np.ndarray, out: np.ndarray | None = None, terms: int = 6
) -> np.ndarray:
    """(3, n, njoint): position, velocity and acceleration of each polynomial at its `s`.

    Args:
      polynomials: (6, n, njoint) coefficients of s^0 .. s^5.
      s: (n,) time since the segment's point (clamped at 0; 0 for a HELD point).
      done: (n,) past the last point: the point's position, at rest.
      out: (3, n, njoint) where to write them, or None.
      terms: the coefficients in use, 4 to 6 (CUBIC_TERMS where no segment is QUINTIC): those
        after are 0.

    Horner's rule over whole coefficient planes: elementwise NumPy only, which ran 2-4 times
    faster than a (3, 6) x (6, njoint) matrix product per segment, and its powers of s, on the
    GPU hosts (benchmarks/RESULTS.md, "The trajectory burst").
    """
    c, m = polynomials, min(max(int(terms), 4), 6)
    if out is None:
        out = np.empty((3, *c.shape[1:]))
    x = np.maximum(s, 0.0)[:, None]
    p, v, a = out
    np.multiply(c[m - 1], x, out=p)  # p = c0 + x (c1 + x (c2 + ...))
    for k in range(m - 2, 0, -1):
        p += c[k]
        p *= x
    p += c[0]
    np.multiply(c[m - 1], (m - 1) * x, out=v)  # v = c1 + x (2 c2 + x (3 c3 + ...))
    for k in range(m - 2, 1, -1):
        v += k * c[k]
        v *= x
    v += c[1]
    np.multiply(c[m - 1], (m - 1) * (m - 2) * x, out=a)  # a = 2 c2 + x (6 c3 + x (12 c4 + ...))
    for k in range(m - 2, 2, -1):
        a += (k * (k - 1)) * c[k]
        a *= x
    a += 2.0 * c[2]
    if done.any():  # past the last point: exactly the point, at rest
        out[0, done] = c[0, done]
        out[1:, done] = 0.0
    return out
