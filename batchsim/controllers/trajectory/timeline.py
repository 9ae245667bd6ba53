"""Every world's trajectory timeline: the queued trajectory, the running one, and the reference.

A world holds at most two trajectories in the segment pool: the one waiting for its start
time and the one running. `queue` stores accepted trajectories as the pending ones, `start`
makes the due ones running from the state the controller measured (inserting it as the
point the first segment leaves from, dropping points already past), and `sample` advances
each world's current segment and evaluates the reference at the update's time. The pool
holds the points as given; a segment's polynomial is made from its two points when time
enters it (the first one's from the start state, when the trajectory starts), or ahead by
`prepare` while the device steps the period before (a first one too, when the state it
leaves from is the reference then), and kept while time stays in it, so
queueing costs a copy of the points and sampling O(worlds).
A world with no running trajectory holds its reference. Goals and commands stay with
the controller: `queue` and `start` return what it needs for them.
"""

from __future__ import annotations

import numpy as np

from batchsim.controllers.base import last_per_world, ranges, rows_all
from batchsim.controllers.trajectory.pool import PENDING, RUNNING, SegmentPool
from batchsim.controllers.trajectory.splines import (
    CUBIC_TERMS,
    HELD,
    QUINTIC,
    evaluate,
    planes_read,
)
from batchsim.controllers.trajectory.validation import Unpacked


class Timeline:
    """Every world's queued and running trajectory, and the reference sampled from them.

    Args:
      nworld, njoint: the fleet and the controller's joints.
      step_points: `interpolation_method: none`: hold each point, no splines.

    Attributes (the running trajectory is block rows 0..last of `pool`, the pending one's
    points rows 1..npoint of its block; row 0 is the start point: its time is filled when
    the trajectory starts, and its values go straight into the first segment's polynomial):
      pool: the SegmentPool holding every world's rows.
      reference_position, reference_velocity, reference_acceleration: (nworld, njoint), the
        reference at the last `sample` (or `stop`).
      executing: (nworld,) bool, a trajectory is running and not yet past its last point.
      hold: (nworld, njoint), the reference of a world with no running trajectory.
      on_trajectory: (nworld,) bool, the reference came from a trajectory (since the last
        stop): a partial goal's other joints then hold the reference, not the measured position.
      running: (nworld,) bool, a trajectory is running.
      t0: (nworld,) float64, its start, sim time.
      segment: (nworld,) int64, the block row time has reached.
      last: (nworld,) int64, its last row.
      spline: (nworld,) int8 Spline of the running trajectory.
      polynomial: (6, nworld, njoint), the polynomial of its segment `made` (splines.coefficients).
      made: (nworld,) int64, the segment `polynomial` is of; -1: none yet.
      version: (nworld,) int64, an id of the polynomial in `polynomial` (each one made has its
        own): a reference `prepare` sampled ahead is taken for the same id, s and end.
      generation: (nworld,) int64, counts the world's queued trajectories, starts and stops: a
        polynomial `prepare` made is taken only for the same generation and segment (and, for
        a first segment, the same start time and state).
      pending_start: (nworld,) float64, the pending trajectory's start time (0: the next
        update), inf for none.
      pending_npoint: (nworld,) int64, its points.
      pending_spline: (nworld,) int8 Spline, its interpolation.
      pending_mask: (nworld, njoint) bool, the joints it names.
    """

    def __init__(self, nworld: int, njoint: int, *, step_points: bool):
        W, nj = nworld, njoint
        self.nworld, self.njoint = nworld, njoint
        self.step_points = step_points
        self.pool = SegmentPool(W, nj)
        self._reference = np.zeros((3, W, nj))  # sampled straight into it when every world runs
        self.reference_position, self.reference_velocity, self.reference_acceleration = self._reference
        self.executing = np.zeros(W, bool)
        self.hold = np.zeros((W, nj))
        self.on_trajectory = np.zeros(W, bool)
        self.running = np.zeros(W, bool)
        self.t0 = np.zeros(W)
        self.segment, self.last = np.zeros(W, np.int64), np.zeros(W, np.int64)
        self.spline = np.zeros(W, np.int8)
        self.polynomial = np.zeros((6, W, nj))
        self.made = np.full(W, -1, np.int64)
        self.version = np.full(W, -1, np.int64)
        self._ids = 0  # the next polynomial's id
        self.generation = np.zeros(W, np.int64)
        # polynomials made ahead (prepare) for the segment and generation each is of (-1: none)
        self._prepared = np.zeros((6, W, nj))
        self._prepared_segment, self._prepared_generation = np.full(W, -1, np.int64), np.full(W, -1, np.int64)
        # or the first segment of the queued trajectory due then: its start time (nan: not one),
        # and the position and velocity it leaves from
        self._prepared_start = np.full(W, np.nan)
        self._prepared_from = np.zeros((2, W, nj))
        self._prepared_version = np.full(W, -1, np.int64)
        # the reference sampled ahead (prepare) and what it was sampled from: polynomial id, s, end
        self._ahead = np.zeros((3, W, nj))
        self._ahead_version = np.full(W, -2, np.int64)
        self._ahead_s, self._ahead_done = np.zeros(W), np.zeros(W, bool)
        self.pending_start = np.full(W, np.inf)
        self.pending_npoint, self.pending_spline = np.zeros(W, np.int64), np.zeros(W, np.int8)
        self.pending_mask = np.zeros((W, nj), bool)

    @property
    def pending(self) -> np.ndarray:
        """(nworld,) bool: a trajectory is queued and waiting for its start time."""
        return np.isfinite(self.pending_start)

    def due(self, time: float) -> np.ndarray:
        """The worlds whose pending trajectory starts at or before `time`, (n,) int64."""
        if self.pending_start.min() > time + 1e-9:  # the usual case: none
            return np.zeros(0, np.int64)
        return np.flatnonzero(self.pending_start <= time + 1e-9)

    def queue(
        self, b: Unpacked, accepted: np.ndarray, spline: np.ndarray, points: tuple[np.ndarray | None, ...]
    ) -> np.ndarray:
        """Store the accepted trajectories (the last per world) as their worlds' pending ones.

        Args:
          b: the batch.
          accepted: (n,) indices into the batch of the accepted trajectories.
          spline: (ntrajectory,) int8 Spline of each trajectory of the batch.
          points: (p, v, a), each (npoint, njoint) or None (all 0): the batch's points, 0
            where not given (validation.Verdict.points).

        Returns:
          (k,) the indices into the batch of the trajectories queued, one per world.
        """
        if not accepted.size:
            return accepted
        keep = accepted[last_per_world(b.worlds[accepted])]
        worlds, npoint = b.worlds[keep], b.counts[keep]
        pool = self.pool
        pool.release(PENDING, worlds)  # a newer goal replaces one still waiting to start
        filled = npoint > 0
        pool.allocate(PENDING, worlds[filled], npoint[filled] + 1)  # + the start row
        off = pool.offset[PENDING, worlds[filled]]
        # the planes the trajectories' segments read (a plane they do not read keeps what it held)
        read = planes_read(np.array([HELD]) if self.step_points else spline[keep])
        everything = int(npoint.sum()) == len(b.times)  # every point kept (the usual case): no gather
        source = slice(None) if everything else ranges(b.offsets[keep][filled], npoint[filled])
        planes = {
            k: 0.0 if values is None else values[source]
            for k, (values, wanted) in enumerate(zip(points, read, strict=True))
            if wanted
        }
        pool.put(off + 1, npoint[filled], b.times[source], planes)
        self.pending_start[worlds] = b.start_time[keep]
        self.pending_npoint[worlds] = npoint
        self.pending_spline[worlds] = spline[keep]
        self.pending_mask[worlds] = b.joint_mask[keep]
        self.generation[worlds] += 1  # a first segment made ahead for the one replaced is not taken
        return keep

    def start(
        self, due: np.ndarray, time: float, here: np.ndarray, here_v: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Make the due worlds' queued trajectories their running ones, from the current state.

        Args:
          due: (n,) the worlds (`due`).
          time: the update's sim time.
          here, here_v: (n, njoint) the position and velocity each trajectory leaves from.

        Returns:
          end: (n,) sim time of each trajectory's last point.
          started: the worlds of `due` now running (the others had no point ahead, and hold).
        """
        t0, off, skip, end = self._leaving(due, time)
        npoint = self.pending_npoint[due]
        stop = skip >= npoint
        if stop.any():
            self._hold_at_end(due[stop], off[stop], npoint[stop], here[stop])
            go = ~stop
            worlds, t0, skip, here, here_v = due[go], t0[go], skip[go], here[go], here_v[go]
        else:  # the usual case: every one has a point ahead
            worlds = due
        if worlds.size:
            self.pool.promote(worlds)
            self._begin(worlds, t0, time, skip, here, here_v)
        self.pending_start[due] = np.inf
        self.pending_npoint[due] = 0
        return end, worlds

    def _leaving(self, due: np.ndarray, time: float) -> tuple[np.ndarray, ...]:
        """For the due worlds' queued trajectories started at `time`: their start t0 (sim
        time), the offset of their pending block, the points already past at `time` (dropped:
        the first segment leaves the row of the last of them, or row 0), and the sim time of
        their last point; each (n,)."""
        pool = self.pool
        t0 = np.where(self.pending_start[due] > 0, self.pending_start[due], time)
        npoint = self.pending_npoint[due]
        off = pool.offset[PENDING, due]
        skip = np.zeros(len(due), np.int64)
        late = npoint > 0
        late[late] = t0[late] + pool.times[off[late] + 1] <= time
        if late.any():  # times increase, so the passed points are a prefix: count them
            passed = ranges(off[late] + 1, npoint[late])
            which = np.repeat(np.arange(int(late.sum())), npoint[late])
            gone = np.repeat(t0[late], npoint[late]) + pool.times[passed] <= time
            skip[late] = np.bincount(which, weights=gone, minlength=int(late.sum())).astype(np.int64)
        end = t0.copy()
        filled = npoint > 0
        end[filled] += pool.times[off[filled] + npoint[filled]]
        return t0, off, skip, end

    def _hold_at_end(self, stopped: np.ndarray, off: np.ndarray, npoint: np.ndarray, here: np.ndarray) -> None:
        """Due trajectories with every point already passed (a single point at time 0, stamped
        now, as ros2_controllers applies at once; or the last point's time gone by before the
        loop took it): the reference is past the end, so it holds the last point; an empty
        trajectory holds `here`."""
        pool = self.pool
        hold = here.copy()
        ended = npoint > 0
        if ended.any():
            last = pool.points[0, off[ended] + npoint[ended]]
            mask = self.pending_mask[stopped[ended]]
            hold[ended] = np.where(mask, last, hold[ended])
        pool.release(RUNNING, stopped)
        pool.release(PENDING, stopped)
        pool.trim(stopped)
        self.running[stopped] = False
        self.on_trajectory[stopped] = False
        self.hold[stopped] = hold
        self.generation[stopped] += 1

    def _begin(
        self,
        worlds: np.ndarray,
        t0: np.ndarray,
        time: float,
        skip: np.ndarray,
        here: np.ndarray,
        here_v: np.ndarray,
    ) -> None:
        """Insert the current point before the first point ahead and set the worlds running."""
        pool = self.pool
        off = pool.offset[RUNNING, worlds]
        npoint = self.pending_npoint[worlds]
        mask = self.pending_mask[worlds]
        start_row = off + skip
        pool.times[start_row] = time - t0
        partial = ~rows_all(mask)
        if partial.any():  # joints a partial goal leaves out go to their reference and hold there
            hold = np.where(
                self.on_trajectory[worlds[partial], None],
                self.reference_position[worlds[partial]],
                here[partial],
            )
            rows = ranges(start_row[partial] + 1, npoint[partial] - skip[partial])
            which = np.repeat(np.arange(len(hold)), npoint[partial] - skip[partial])
            block = pool.points[:, rows]  # (3, n, nj)
            out = ~mask[partial][which]
            block[:, out] = 0.0
            block[0, out] = hold[which][out]
            pool.points[:, rows] = block
        self.t0[worlds] = t0
        self.segment[worlds] = skip
        self.last[worlds] = npoint
        self.spline[worlds] = self.pending_spline[worlds]
        self._first_segments(worlds, skip, start_row, time, here, here_v)
        self.made[worlds] = skip
        self.running[worlds] = True
        self.on_trajectory[worlds] = True
        self.generation[worlds] += 1

    def sample(self, time: float) -> None:
        """Reference position/velocity/acceleration of every world at `time`."""
        pos, vel, acc = self.reference_position, self.reference_velocity, self.reference_acceleration
        running = np.flatnonzero(self.running)
        if len(running) < self.nworld:
            pos[:] = self.hold
            vel[:] = 0.0
            acc[:] = 0.0
            self.executing[:] = False
        if not running.size:
            return
        pool = self.pool
        times = pool.times
        rel = time - self.t0[running]
        base = pool.offset[RUNNING, running]
        last = self.last[running]
        segment = self._segment_at(running, base, rel)
        self.segment[running] = segment
        row = base + segment
        done = segment >= last  # past the last point: its position, at rest
        entered = np.flatnonzero(self.made[running] != segment)
        if entered.size:  # the segments time entered since the last update: their polynomials
            self._enter(running[entered], segment[entered], row[entered], done[entered])
        s = np.zeros(len(running)) if self.step_points else rel - times[row]  # a held point: as it is
        every = len(running) == self.nworld
        ahead = (
            (self._ahead_version[running] == self.version[running])
            & (self._ahead_done[running] == done)
            & (self._ahead_s[running] == s)  # sampled for this very time
        )
        if ahead.all():  # sampled by prepare, from the same polynomials
            if every:
                np.copyto(self._reference, self._ahead)
            else:
                self._reference[:, running] = self._ahead[:, running]
        elif every and not ahead.any():  # straight into place
            evaluate(self.polynomial, s, done, out=self._reference, terms=self._terms(self.spline))
        else:
            taken, rest = running[ahead], running[~ahead]
            self._reference[:, taken] = self._ahead[:, taken]
            self._reference[:, rest] = evaluate(self.polynomial[:, rest], s[~ahead], done[~ahead], terms=self._terms(self.spline[rest]))
        self.executing[running] = ~done
        finished = running[done]
        if finished.size:  # past the last point: hold it and give the rows back
            self.hold[finished] = pos[finished]
            self.running[finished] = False
            pool.release(RUNNING, finished)
            pool.trim(finished)

    def prepare(self, time: float, starts: bool = False) -> None:
        """Make ahead what the next update (at `time`) would make, so that it only takes it: the
        polynomials of the segments running worlds will have entered (a fleet whose trajectories
        run in step enters new segments all in one period); with `starts` (the trajectories
        leave from the reference: open_loop_control) the first segments of the queued ones due
        by then, from the reference now; and the reference those polynomials give at `time`.
        Host work only, while the device steps (Controller.prepare). A world that queues, starts
        or stops meanwhile has a new generation, and makes its own; so does a start from
        another state or at another time (SimLoop's next update comes at `time` exactly); a
        reference is taken only from the same polynomial, s and end."""
        due = np.isfinite(self.pending_start) & (self.pending_start <= time + 1e-9)
        running = np.flatnonzero(self.running & ~due)
        base = self.pool.offset[RUNNING, running]
        segment = self._segment_at(running, base, time - self.t0[running])
        done = segment >= self.last[running]  # past the last point: its position, at rest
        entering = segment != self.made[running]
        ahead = np.flatnonzero(entering)
        if ahead.size:
            worlds = running[ahead]
            self._make(worlds, base[ahead] + segment[ahead], done[ahead], into=self._prepared)
            self._prepared_segment[worlds] = segment[ahead]
            self._prepared_generation[worlds] = self.generation[worlds]
            self._prepared_start[worlds] = np.nan
        due = np.flatnonzero(due & rows_all(self.pending_mask)) if starts else np.zeros(0, np.int64)  # partial: at the start
        if due.size:
            t0, off, skip, _ = self._leaving(due, time)
            go = skip < self.pending_npoint[due]  # the others hold their last point
            due, row = due[go], (off + skip)[go]
            every = len(due) == self.nworld
            here = self._reference[:2] if every else self._reference[:2, due]
            self._make(due, row, np.zeros(len(due), bool), start=(here[0], here[1]), into=self._prepared,
                       spline=self.pending_spline[due], leave=time - t0[go])
            self._prepared_segment[due] = skip[go]
            self._prepared_generation[due] = self.generation[due]
            self._prepared_start[due] = time
            if every:
                np.copyto(self._prepared_from, here)
            else:
                self._prepared_from[:, due] = here
        # the reference at `time`: from the polynomial kept, or the one made above (a segment
        # entered, a trajectory started: s = 0 there); none where the update makes its own
        s = np.zeros(len(running)) if self.step_points else time - self.t0[running] - self.pool.times[base + segment]
        kept = running[~entering]
        self._sample_ahead(kept, self.version[kept], s[~entering], done[~entering], self.spline[kept], self.polynomial)
        made, spline = np.concatenate([running[ahead], due]), np.concatenate([self.spline[running[ahead]], self.pending_spline[due]])
        s, done = np.concatenate([s[ahead], np.zeros(len(due))]), np.concatenate([done[ahead], np.zeros(len(due), bool)])
        self._sample_ahead(made, self._prepared_version[made], s, done, spline, self._prepared)

    def _sample_ahead(
        self, worlds: np.ndarray, version: np.ndarray, s: np.ndarray, done: np.ndarray, spline: np.ndarray, polynomial: np.ndarray
    ) -> None:
        """The reference of the worlds' polynomials (of Splines `spline`) in `polynomial` at `s`
        (`done`: past the last point) into `_ahead`, keyed by the polynomials' ids (prepare)."""
        if not worlds.size:
            return
        terms = self._terms(spline)  # as sample takes them: the same rounding
        if len(worlds) == self.nworld and (worlds[1:] > worlds[:-1]).all():  # every world, in order
            evaluate(polynomial, s, done, out=self._ahead, terms=terms)
        else:
            self._ahead[:, worlds] = evaluate(polynomial[:, worlds], s, done, terms=terms)
        self._ahead_version[worlds] = version
        self._ahead_s[worlds] = s
        self._ahead_done[worlds] = done

    @staticmethod
    def _terms(spline: np.ndarray) -> int:  # the coefficients `evaluate` needs for these Splines
        return 6 if (spline == QUINTIC).any() else CUBIC_TERMS

    def _segment_at(self, running: np.ndarray, base: np.ndarray, rel: np.ndarray) -> np.ndarray:
        """(n,) the segment each of the running worlds is in at `rel` (time since its start): the
        last point at or before it, from the current one on (usually the same or the next)."""
        times = self.pool.times
        segment, last = self.segment[running], self.last[running]
        moving = np.flatnonzero((segment < last) & (times[base + np.minimum(segment + 1, last)] <= rel + 1e-12))
        while moving.size:
            segment[moving] += 1
            s = segment[moving]
            ahead = (s < last[moving]) & (times[base[moving] + np.minimum(s + 1, last[moving])] <= rel[moving] + 1e-12)
            moving = moving[ahead]
        return segment

    def _enter(self, worlds: np.ndarray, segment: np.ndarray, row: np.ndarray, done: np.ndarray) -> None:
        """The worlds' polynomials for the segments they entered: those `prepare` made for the
        same segment and generation, else made now."""
        ready = (
            (self._prepared_segment[worlds] == segment)
            & (self._prepared_generation[worlds] == self.generation[worlds])
            & np.isnan(self._prepared_start[worlds])
        )
        if ready.all() and len(worlds) == self.nworld:
            self._take_all_prepared()
        else:
            if ready.any():
                taken = worlds[ready]
                self.polynomial[:, taken] = self._prepared[:, taken]
                self.version[taken] = self._prepared_version[taken]
            if not ready.all():
                self._make(worlds[~ready], row[~ready], done[~ready])
        self._prepared_segment[worlds] = -1
        self.made[worlds] = segment

    def _take_all_prepared(self) -> None:
        """Every world takes what prepare made: the blocks trade places, not copied (the caller
        marks `_prepared` stale)."""
        self.polynomial, self._prepared = self._prepared, self.polynomial
        self.version, self._prepared_version = self._prepared_version, self.version

    def _first_segments(
        self,
        worlds: np.ndarray,
        skip: np.ndarray,
        row: np.ndarray,
        time: float,
        here: np.ndarray,
        here_v: np.ndarray,
    ) -> None:
        """The starting worlds' first polynomials, leaving block row `skip` (pool row `row`) from
        `here`, `here_v`: those `prepare` made for the same row, generation, start time (exactly)
        and state (never a partial goal's: its other joints' points change at the start), else
        made now."""
        every = len(worlds) == self.nworld  # (in order: `due`)
        ready = (
            (self._prepared_segment[worlds] == skip)
            & (self._prepared_generation[worlds] == self.generation[worlds])
            & (self._prepared_start[worlds] == time)  # nan: not a first segment
        )
        if ready.any():  # (none in closed loop: no state compared)
            made_from = self._prepared_from if every else self._prepared_from[:, worlds]
            if not ((made_from[0] == here).all() and (made_from[1] == here_v).all()):  # (a tenth of a per-row test)
                ready &= rows_all(made_from[0] == here) & rows_all(made_from[1] == here_v)
        self._prepared_segment[worlds] = -1
        if ready.all() and every:  # a burst made ahead
            self._take_all_prepared()
            return
        if ready.any():
            taken = worlds[ready]
            self.polynomial[:, taken] = self._prepared[:, taken]
            self.version[taken] = self._prepared_version[taken]
        if not ready.all():
            rest = ~ready
            self._make(worlds[rest], row[rest], np.zeros(int(rest.sum()), bool), start=(here[rest], here_v[rest]))

    def _make(
        self,
        worlds: np.ndarray,
        row: np.ndarray,
        done: np.ndarray,
        start: tuple[np.ndarray, np.ndarray] | None = None,
        into: np.ndarray | None = None,
        spline: np.ndarray | None = None,
        leave: np.ndarray | None = None,
    ) -> None:
        """The worlds' polynomials (SegmentPool.polynomials, of their running trajectory's kind or
        `spline`), into their place in `into` ((6, nworld, njoint): `polynomial`, or `_prepared`
        for prepare), each with a new id in `version` or `_prepared_version`."""
        if self.step_points:  # each point as it is
            kind, leave = np.full(len(worlds), HELD, np.int8), None
        else:
            kind = self.spline[worlds] if spline is None else spline
        into = self.polynomial if into is None else into
        if len(worlds) == self.nworld:  # every world (a burst): straight into place
            self.pool.polynomials(kind, row, done, start, leave, out=into)
        else:
            into[:, worlds] = self.pool.polynomials(kind, row, done, start, leave)
        ids = self._ids + np.arange(len(worlds))
        self._ids += len(worlds)
        (self.version if into is self.polynomial else self._prepared_version)[worlds] = ids

    def stop(self, worlds: np.ndarray, position: np.ndarray) -> None:
        """Drop the worlds' trajectories, running and queued, and hold them at `position`
        ((n, njoint), or anything that broadcasts to it)."""
        self.pool.release(RUNNING, worlds)
        self.pool.release(PENDING, worlds)
        self.pool.trim(worlds)
        self.running[worlds] = False
        self.on_trajectory[worlds] = False
        self.hold[worlds] = position
        self.reference_position[worlds] = position
        self.reference_velocity[worlds] = 0.0
        self.reference_acceleration[worlds] = 0.0
        self.executing[worlds] = False
        self.pending_start[worlds] = np.inf
        self.pending_npoint[worlds] = 0
        self.generation[worlds] += 1
