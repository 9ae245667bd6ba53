"""The trajectory controller's segment pool: every world's trajectory rows in one flat array.

Memory follows each world's own trajectory: a block of rows per world and trajectory
(running, pending, and a spare kept for reuse), carved from one array that is copied into
a right-sized one only when it fills or empties.
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import as_strided

from batchsim.controllers.base import ranges
from batchsim.controllers.trajectory.splines import HELD, coefficients, planes_read

# the blocks of pool rows a world may hold: rows of SegmentPool.offset and .size
RUNNING = 0  # the trajectory being followed
PENDING = 1  # the one waiting for its start time
SPARE = 2  # a released block, kept for the world's next trajectory
SPARE_ROWS = 64  # a spare up to this many rows stays with its world until it is reused
MIN_POOL_ROWS = 256


class SegmentPool:
    """Every world's trajectory rows in one flat array, a block of contiguous rows per trajectory.

    Row r of a block is point r: `times[r]` its time from the trajectory's start and
    `points[:, r]` its position, velocity and acceleration (the segment that leaves it runs
    to row r + 1). Blocks are carved from the end of the used rows. A released block
    becomes its world's spare, reused by its next trajectory if that needs between half of
    it and all of it (or it is small), so a fleet streaming trajectories reuses rows
    instead of allocating; a spare larger than SPARE_ROWS is freed when it does not fit
    that way, or when the world's trajectory ends.
    When the end of the array is reached, or fewer than a quarter of its rows are held, the
    held blocks are copied into a right-sized array.

    Attributes:
      times: (capacity,) float64.
      points: (3, capacity, njoint) float64: the position, velocity and acceleration planes.
      offset: (3, nworld) int64, the first row of each world's running, pending and spare
        block, -1 for none.
      size: (3, nworld) int64, the rows each of those blocks holds.
      held: rows in blocks some world holds.
    """

    def __init__(self, nworld: int, njoint: int):
        self.njoint = njoint
        self.times = np.zeros(0)
        self.points = np.zeros((3, 0, njoint))
        self.offset = np.full((3, nworld), -1, np.int64)
        self.size = np.zeros((3, nworld), np.int64)
        self.held = 0
        self.used = 0  # rows handed out from the start of the array, held or not

    @property
    def capacity(self) -> int:
        return len(self.times)

    def release(self, kind: int, worlds: np.ndarray) -> None:
        """Give up the `kind` blocks of `worlds` (each listed once): each becomes its world's
        spare if larger than the one it has (which is then freed), or is freed."""
        held = self.offset[kind, worlds] >= 0
        if not held.all():
            worlds = worlds[held]
            if not worlds.size:
                return
        off, size = self.offset[kind, worlds], self.size[kind, worlds]
        self.offset[kind, worlds] = -1
        self.size[kind, worlds] = 0
        keep = size > self.size[SPARE, worlds]
        kept = worlds[keep]
        self.held -= int(size[~keep].sum()) + int(self.size[SPARE, kept].sum())
        self.offset[SPARE, kept] = off[keep]
        self.size[SPARE, kept] = size[keep]

    def trim(self, worlds: np.ndarray, rows: np.ndarray | int = 0) -> None:
        """Free the spares of `worlds` larger than SPARE_ROWS and than twice `rows` (the size of
        the trajectory each world now has): memory follows the trajectories."""
        size = self.size[SPARE, worlds]
        if not size.size or size.max() <= SPARE_ROWS:  # the usual case: nothing to free
            return
        large = worlds[(size > SPARE_ROWS) & (size > 2 * np.asarray(rows))]
        self.held -= int(self.size[SPARE, large].sum())
        self.offset[SPARE, large] = -1
        self.size[SPARE, large] = 0

    def promote(self, worlds: np.ndarray) -> None:
        """The pending blocks of `worlds` become their running ones; the running ones are released."""
        self.release(RUNNING, worlds)
        self.offset[RUNNING, worlds] = self.offset[PENDING, worlds]
        self.size[RUNNING, worlds] = self.size[PENDING, worlds]
        self.offset[PENDING, worlds] = -1
        self.size[PENDING, worlds] = 0
        self.trim(worlds, self.size[RUNNING, worlds])  # a large block replaced by a small one goes

    def allocate(self, kind: int, worlds: np.ndarray, rows: np.ndarray) -> None:
        """Blocks of `rows` rows for `worlds` (each listed once, with no `kind` block yet)."""
        self.trim(worlds, rows)  # a large spare the new trajectory would not half fill goes
        fits = self.size[SPARE, worlds] >= rows
        reuse = worlds[fits]
        self.offset[kind, reuse] = self.offset[SPARE, reuse]
        self.size[kind, reuse] = self.size[SPARE, reuse]
        self.offset[SPARE, reuse] = -1
        self.size[SPARE, reuse] = 0
        if len(reuse) == len(worlds):  # the usual case, streaming: every spare served
            return
        new, need = worlds[~fits], rows[~fits]
        total = int(need.sum())
        if not total:
            return
        if self.used + total > self.capacity:
            self._compact(total)
        self.offset[kind, new] = self.used + np.cumsum(need) - need
        self.size[kind, new] = need
        self.used += total
        self.held += total

    def put(
        self, starts: np.ndarray, counts: np.ndarray, times: np.ndarray, planes: dict[int, np.ndarray | float]
    ) -> None:
        """Fill blocks of rows: rows starts[i] .. starts[i] + counts[i] - 1 get the i-th block
        of `times` (sum(counts),) and of each plane's values ({plane: (sum(counts), njoint),
        or a number for every row}); the other planes keep what they held."""
        put_blocks(self.times, starts, counts, times)
        for k, values in planes.items():
            put_blocks(self.points[k], starts, counts, values)

    def ends(self, rows: np.ndarray, planes: np.ndarray, start: bool = False) -> np.ndarray:
        """(6, n, njoint), splines.ENDS (p0, p1, v0, v1, a0, a1): the position, velocity and
        acceleration of the points at `rows` and at the row after each (the two ends of the
        segments that leave `rows`), of the planes (3,) bool asked for; the others are left
        uninitialized, and so are the points at `rows` with `start` (the caller's start point)."""
        out = np.empty((6, len(rows), self.njoint))
        after = rows + 1
        for k in np.flatnonzero(planes).tolist():
            if not start:
                np.take(self.points[k], rows, axis=0, out=out[2 * k])
            np.take(self.points[k], after, axis=0, out=out[2 * k + 1])
        return out

    def polynomials(
        self,
        kind: np.ndarray,
        rows: np.ndarray,
        done: np.ndarray,
        start: tuple[np.ndarray, np.ndarray] | None = None,
        leave: np.ndarray | None = None,
        out: np.ndarray | None = None,
    ) -> np.ndarray:
        """(6, n, njoint): the polynomials (splines.coefficients) of the segments that leave `rows`,
        of kind `kind` (n,) Spline or HELD (the point as it is); past the last point (`done`),
        that point's position. `start`: (n, njoint) the position and velocity they leave from
        (at rest otherwise) instead of the row's point; `leave`: (n,) the time of `rows` (a
        queued trajectory's first segment, made before it starts: then the row holds a passed
        point's or nothing). `out`: where to write them ((6, n, njoint), C-contiguous)."""
        n = len(rows)
        polynomial = np.empty((6, n, self.njoint)) if out is None else out
        go: slice | np.ndarray = slice(None)
        if done.any():
            polynomial[:, done] = 0.0
            polynomial[0, done] = self.points[0, rows[done]]
            go = np.flatnonzero(~done)
        r, kind = rows[go], kind[go]
        if len(r):
            if (kind == HELD).all():
                T = np.ones(len(r))
            else:
                T = self.times[r + 1] - (self.times[r] if leave is None else leave[go])
            ends = self.ends(r, planes_read(kind), start=start is not None)  # (6, n, nj): splines.ENDS
            if start is not None:  # p0, v0, a0
                ends[0], ends[2], ends[4] = start[0][go], start[1][go], 0.0
            if len(r) == n:
                coefficients(kind, ends, T, out=polynomial)
            else:
                polynomial[:, go] = coefficients(kind, ends, T)
        return polynomial

    def shrink(self) -> None:
        """Copy the held blocks into a smaller array when most rows are no longer held."""
        if self.capacity > MIN_POOL_ROWS and self.held < self.capacity // 4:
            self._compact(0)

    def _compact(self, extra: int) -> None:
        kinds, worlds = np.nonzero(self.offset >= 0)
        off, size = self.offset[kinds, worlds], self.size[kinds, worlds]
        total = int(size.sum())
        capacity = max(MIN_POOL_ROWS, 2 * (total + extra))  # room for as much again before the next copy
        times = np.zeros(capacity)
        points = np.zeros((3, capacity, self.njoint))
        source = ranges(off, size)
        times[:total] = self.times[source]
        points[:, :total] = self.points[:, source]
        self.offset[kinds, worlds] = np.cumsum(size) - size
        self.times, self.points = times, points
        self.used = self.held = total


def put_blocks(
    target: np.ndarray, starts: np.ndarray, counts: np.ndarray, values: np.ndarray | float
) -> None:
    """target[starts[i] : starts[i] + counts[i]] = the i-th block of `values` (CSR by counts),
    along the first axis of a C-contiguous `target`; blocks of one length (a batch of equal
    trajectories: the usual case) go as one row each of a window onto `target`."""
    if not len(counts):
        return
    size = int(counts[0])
    if size < 1 or (counts != size).any() or size > len(target):
        target[ranges(starts, counts)] = values
        return
    row, item = target.strides[0], target.itemsize  # row r of the window: target rows r .. r + size - 1
    window = as_strided(target, (len(target) - size + 1, size * row // item), (row, item))
    window[starts] = values if np.ndim(values) == 0 else np.reshape(values, (len(counts), -1))
