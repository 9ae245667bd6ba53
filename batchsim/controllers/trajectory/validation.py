"""A TrajectoryBatch unpacked and checked, as the trajectory controller accepts it.

`unpack` types and shape-checks the batch's arrays (a malformed batch is the sender's bug:
ValueError); `check` runs every per-trajectory check vectorized over the batch and names
the reason of each rejected trajectory; `CommandBound` bounds the commands a reference
gives, so that no accepted trajectory can command MAX_COMMAND or more, which write()
would refuse.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from batchsim.controllers.base import rows_all
from batchsim.controllers.joint_names import JointOrder
from batchsim.controllers.topics import TrajectoryBatch
from batchsim.controllers.trajectory.splines import coefficients, spline_of
from batchsim.types import MAX_COMMAND, world_out_of_range


@dataclasses.dataclass
class Unpacked:
    """A TrajectoryBatch's arrays, typed and checked (see TrajectoryBatch); worlds out of range are 0."""

    worlds_given: np.ndarray
    worlds: np.ndarray
    bad_world: np.ndarray
    start_time: np.ndarray
    joint_mask: np.ndarray
    offsets: np.ndarray
    counts: np.ndarray  # (n,) points per trajectory
    times: np.ndarray
    steps: np.ndarray  # (npoint - 1,) times[1:] - times[:-1]
    positions: np.ndarray
    velocities: np.ndarray | None
    has_velocities: np.ndarray
    accelerations: np.ndarray | None
    has_accelerations: np.ndarray
    goals: np.ndarray  # (n,) int64, 0: a topic trajectory
    path_tolerance: np.ndarray | None  # (n, njoint, 3) or None: every goal takes the defaults
    goal_tolerance: np.ndarray | None  # likewise
    goal_time_tolerance: np.ndarray | None  # (n,) or None


@dataclasses.dataclass
class Verdict:
    """What `check` found.

    Attributes:
      failed: (n,) bool, the rejected trajectories.
      rejected: (index in the batch, reason) of each, in batch order.
      spline: (n,) int8 Spline of each trajectory.
      owner: (npoint,) the trajectory of each point.
      points: (p, v, a), each (npoint, njoint): the points' values, 0 where not given; v or
        a None where no point gives it (all 0). Read only: they may be the batch's own.
    """

    failed: np.ndarray
    rejected: list[tuple[int, str]]
    spline: np.ndarray
    owner: np.ndarray
    points: tuple[np.ndarray | None, ...]


@dataclasses.dataclass(frozen=True)
class CommandBound:
    """A bound on the commands, from bounds on the reference's position, velocity and acceleration.

    Attributes:
      kinds: the command interfaces, in claim order ("position", "velocity", ...).
      pid: a lone velocity or effort interface, commanded through a PID.
      kv: (njoint,) |ff_velocity_scale| + |d| of the PID.
      kp: (njoint,) |p| of the PID.
    """

    kinds: tuple[str, ...]
    pid: bool
    kv: np.ndarray
    kp: np.ndarray

    def __call__(self, position: np.ndarray, velocity: np.ndarray, acceleration: np.ndarray) -> np.ndarray:
        if self.pid:  # the measured state adds what the PID makes of it: physical, so small
            kv, kp = self.kv, self.kp
            if np.ndim(position) < 2:  # one bound for every joint
                kv, kp = kv.max(), kp.max()
            return kv * velocity + kp * position
        reference = {"position": position, "velocity": velocity, "acceleration": acceleration}
        return np.maximum.reduce([reference[kind] for kind in self.kinds])


def unpack(batch: TrajectoryBatch, *, name: str, nworld: int, njoint: int) -> Unpacked:
    """The batch's arrays, typed and shape-checked; ValueError naming what is malformed."""
    nj = njoint

    def malformed(what: str) -> ValueError:
        return ValueError(f"{name}: malformed TrajectoryBatch: {what}")

    given = np.asarray(batch.worlds).reshape(-1)
    n = given.size
    if given.dtype.kind in "iu":
        integral = np.ones(n, bool)
    elif given.dtype.kind == "f":
        integral = np.isfinite(given) & (given == np.round(given))
    else:
        raise malformed(f"worlds must be integers, got {given.dtype}")
    worlds = np.where(integral, given, -1).astype(np.int64)
    bad_world = ~integral | (worlds < 0) | (worlds >= nworld)
    worlds[bad_world] = 0

    def array(value: Any, shape: tuple[int, ...], dtype: Any, what: str) -> np.ndarray:
        a = np.asarray(value, dtype=dtype)
        if a.shape != shape:
            raise malformed(f"{what} must have shape {shape}, got {a.shape}")
        return a

    offsets = array(batch.offsets, (n + 1,), np.int64, "offsets")
    counts = np.diff(offsets)
    if offsets[0] != 0 or (counts < 0).any():
        raise malformed("offsets must start at 0 and never decrease")
    npoint = int(offsets[-1])
    start = array(batch.start_time, (n,), np.float64, "start_time")
    mask = array(batch.joint_mask, (n, nj), bool, "joint_mask")
    times = array(batch.times, (npoint,), np.float64, "times")
    positions = array(batch.positions, (npoint, nj), np.float64, "positions")
    tables: list[Any] = []
    for values, has, what in (
        (batch.velocities, batch.has_velocities, "velocities"),
        (batch.accelerations, batch.has_accelerations, "accelerations"),
    ):
        if values is None:
            tables += [None, np.zeros(n, bool)]
            continue
        tables.append(array(values, (npoint, nj), np.float64, what))
        tables.append(np.ones(n, bool) if has is None else array(has, (n,), bool, f"has_{what}"))
    goals = np.zeros(n, np.int64) if batch.goals is None else array(batch.goals, (n,), np.int64, "goals")
    if (goals < 0).any():
        raise malformed(f"goals must be >= 0 (0: no goal), got {int(goals.min())}")
    path = (
        None
        if batch.path_tolerance is None
        else array(batch.path_tolerance, (n, nj, 3), np.float64, "path_tolerance")
    )
    goal = (
        None
        if batch.goal_tolerance is None
        else array(batch.goal_tolerance, (n, nj, 3), np.float64, "goal_tolerance")
    )
    goal_time = (
        None
        if batch.goal_time_tolerance is None
        else array(batch.goal_time_tolerance, (n,), np.float64, "goal_time_tolerance")
    )
    steps = np.diff(times)
    return Unpacked(
        given, worlds, bad_world, start, mask, offsets, counts, times, steps, positions, *tables,
        goals, path, goal, goal_time,
    )  # fmt: skip


def one_trajectory(
    world: int,
    joint_names: Sequence[str],
    times: Sequence[float],
    positions: Any,
    velocities: Any,
    accelerations: Any,
    start_time: float,
    *,
    name: str,
    joints: Sequence[str],
) -> TrajectoryBatch:
    """A one-trajectory batch from a JointTrajectory's fields in the message's joint order
    (see JointTrajectoryController.set_trajectory); ValueError for an unknown or repeated
    joint name or a table of the wrong shape."""
    names = list(joint_names)
    order = JointOrder(joints)
    try:
        cols = order.columns(names)
    except ValueError as e:
        raise ValueError(f"{name}: {e}") from None
    mask = order.mask(cols)
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    n, nj = t.size, len(joints)

    def table(values: Any, what: str, required: bool) -> np.ndarray | None:
        if values is None or (np.size(values) == 0 and not required):
            return None
        try:
            a = np.asarray(values, dtype=np.float64)
        except ValueError:
            raise ValueError(f"{name}: every point's {what} must have {len(names)} values") from None
        if a.shape != (n, len(names)):
            raise ValueError(f"{name}: {what} must be {n} points x {len(names)} joints, got shape {a.shape}")
        full = np.zeros((n, nj))
        full[:, cols] = a
        return full

    if n == 0:  # an empty trajectory stops the world: its points' fields do not matter
        p, v, a = np.zeros((0, nj)), None, None
    else:
        p = table(positions, "positions", True)
        v = table(velocities, "velocities", False)
        a = table(accelerations, "accelerations", False)
    return TrajectoryBatch(
        worlds=np.array([world]),
        start_time=np.array([start_time], dtype=np.float64),
        joint_mask=mask[None],
        offsets=np.array([0, n]),
        times=t,
        positions=p,
        velocities=v,
        accelerations=a,
    )


def check(
    b: Unpacked,
    *,
    name: str,
    nworld: int,
    joints: Sequence[str],
    allow_partial: np.ndarray,
    max_points: int,
    time: float,
    bound: CommandBound,
    step_points: bool,
) -> Verdict:
    """Every check of every trajectory of the batch, in one vectorized pass.

    A rejected trajectory's reason names the first check it fails, in the order of the
    controller's documentation; `name` prefixes every reason. `allow_partial`: (n,) bool, each
    trajectory's world's allow_partial_joints_goal.
    """
    n, npoint = len(b.worlds), len(b.times)
    counts = b.counts
    owner = np.repeat(np.arange(n), counts)  # (npoint,) the trajectory of each point
    empty = counts == 0

    def per_trajectory(bad_point: np.ndarray) -> np.ndarray:
        return np.bincount(owner, weights=bad_point, minlength=n) > 0

    # the checks of single points: one pass over the points, the per-check split only if needed
    points = _points(b, owner)
    # the largest |value| of the batch's positions, velocities, accelerations (NaN: NaN): the
    # points' own only when some is not below MAX_COMMAND (the usual batch: none)
    largest = np.array([_largest(x) for x in points])
    magnitude = None if (largest < MAX_COMMAND).all() else _magnitude(points)
    disorder = np.zeros(npoint, bool)  # a point not after the one before it
    disorder[1:] = ~(b.steps > 0) & (owner[1:] == owner[:-1])
    fine = np.zeros(npoint, bool)
    point_checks = [
        ~(np.isfinite(b.times) & (b.times >= 0)),
        disorder,
        *(3 * [fine] if magnitude is None else ~(magnitude < MAX_COMMAND)),  # positions, velocities, accel.
    ]
    none = np.zeros(n, bool)
    if np.logical_or.reduce(point_checks).any():
        bad_time, bad_order, bad_p, bad_v, bad_a = (per_trajectory(c) for c in point_checks)
    else:
        bad_time = bad_order = bad_p = bad_v = bad_a = none
    last_time = b.times[np.maximum(b.offsets[1:] - 1, 0)] if npoint else np.zeros(n)
    # (failing trajectories, reason for one of them): the first that fails names the reason
    checks = [
        (b.bad_world, lambda k: world_out_of_range(b.worlds_given[k], nworld)),
        (~np.isfinite(b.start_time), lambda k: f"start time must be finite, got {b.start_time[k]}"),
        (
            # upstream rejects an action goal with no points; an empty topic trajectory stops the world
            empty & (b.goals != 0),
            lambda k: "the goal's trajectory has no points",
        ),
        (
            ~empty & ~rows_all(b.joint_mask) & ~allow_partial,
            lambda k: (
                f"the trajectory lacks joint {joints[int(np.argmin(b.joint_mask[k]))]!r} and "
                "allow_partial_joints_goal is false"
            ),
        ),
        (
            counts > max_points,
            lambda k: (
                f"the trajectory has {counts[k]} points, more than max_trajectory_points ({max_points})"
            ),
        ),
        (
            bad_time,
            lambda k: (
                "time_from_start must be finite and >= 0, got "
                f"{b.times[b.offsets[k] : b.offsets[k + 1]].tolist()}"
            ),
        ),
        (bad_order, lambda k: _order_reason(b, k)),
        (bad_p, lambda k: _value_reason(b, k, "positions")),
        (bad_v, lambda k: _value_reason(b, k, "velocities")),
        (
            b.has_accelerations & ~b.has_velocities,
            lambda k: "points give accelerations without velocities",
        ),
        (bad_a, lambda k: _value_reason(b, k, "accelerations")),
        (
            ~empty & (b.start_time > 0) & (b.start_time + last_time < time),
            lambda k: (
                f"the trajectory ends at {b.start_time[k] + last_time[k]:g} s, before the "
                f"current time {time:g} s"
            ),
        ),
    ]
    failed = np.logical_or.reduce([bad for bad, _ in checks])
    rejected: dict[int, str] = {}
    if failed.any():
        for k in np.flatnonzero(failed).tolist():  # the first check it fails names the reason
            reason = next(reason for bad, reason in checks if bad[k])
            rejected[k] = f"{name}: {reason(k)}"

    spline = spline_of(b.has_velocities, b.has_accelerations)
    reach = _reach(b, owner, spline, points, largest, magnitude, failed | empty, bound, step_points)
    far = ~(reach < MAX_COMMAND)
    too_far = (per_trajectory(far) if far.any() else none) & ~failed
    for k in np.flatnonzero(too_far).tolist():
        point = int(np.argmax(~(reach[b.offsets[k] : b.offsets[k + 1]] < MAX_COMMAND)))
        where = "the start (from rest)" if point == 0 else f"point {point - 1}"
        rejected[k] = (
            f"{name}: between {where} and point {point} the trajectory's commands may reach "
            f"{reach[b.offsets[k] + point]:.3g} (a bound), beyond the {MAX_COMMAND:g} write() accepts"
        )
    failed |= too_far
    return Verdict(failed, sorted(rejected.items()), spline, owner, points)


def _order_reason(b: Unpacked, k: int) -> str:
    t = b.times[b.offsets[k] : b.offsets[k + 1]]
    i = int(np.flatnonzero(~(np.diff(t) > 0))[0]) + 1
    return (
        f"time_from_start must be strictly increasing: point {i} at {t[i]:g} s "
        f"follows point {i - 1} at {t[i - 1]:g} s"
    )


def _value_reason(b: Unpacked, k: int, what: str) -> str:
    values = getattr(b, what)[b.offsets[k] : b.offsets[k + 1]][:, b.joint_mask[k]]
    if not np.isfinite(values).all():
        return f"{what} must be finite"
    worst = float(values.flat[np.argmax(np.abs(values))])
    return (
        f"{what} must be below {MAX_COMMAND:g} in magnitude (write() refuses larger commands), got {worst:g}"
    )


def _points(b: Unpacked, owner: np.ndarray) -> tuple[np.ndarray | None, ...]:
    """(p, v, a), each (npoint, njoint): the points' values, 0 for joints or fields not
    given; v or a None where no point gives it (the batch's own arrays where it gives
    every one: read only)."""
    named = None if b.joint_mask.all() else b.joint_mask[owner]  # (npoint, nj)

    def given(values: np.ndarray | None, has: np.ndarray) -> np.ndarray | None:
        if values is None or not has.any():
            return None
        if has.all():
            return values if named is None else np.where(named, values, 0.0)
        out = values.copy() if named is None else np.where(named, values, 0.0)
        out[~has[owner]] = 0.0
        return out

    p = b.positions if named is None else np.where(named, b.positions, 0.0)
    return p, given(b.velocities, b.has_velocities), given(b.accelerations, b.has_accelerations)


def _largest(x: np.ndarray | None) -> float:
    """The largest |value| of a (npoint, njoint) table of points (None: 0); NaN: NaN."""
    return 0.0 if x is None else float(np.maximum(x.max(initial=0.0), -x.min(initial=0.0)))


def _magnitude(points: tuple[np.ndarray | None, ...]) -> np.ndarray:
    """(3, npoint): the largest |value| of each point's p, v and a; NaN: NaN."""
    npoint = len(points[0])
    return np.stack([np.zeros(npoint) if x is None else np.abs(x).max(axis=1, initial=0.0) for x in points])


def _reach(
    b: Unpacked,
    owner: np.ndarray,
    spline: np.ndarray,
    points: tuple[np.ndarray | None, ...],
    largest: np.ndarray,
    magnitude: np.ndarray | None,
    skip: np.ndarray,
    bound: CommandBound,
    step_points: bool,
) -> np.ndarray:
    """(npoint,) a bound on the commands the segment ending at each point gives (the first
    point's: from rest at time 0); 0 for the points of `skip` and first points at time 0.

    A cheap bound from the segment's end values screens every segment; the polynomial's
    own bound is computed only for the few the cheap one cannot clear. `largest`: (3,) the
    batch's largest |p|, |v|, |a|; `magnitude`: (3, npoint) each point's (`_magnitude`), or
    None when not computed yet.
    """
    p = points[0]
    npoint = len(p)
    if npoint == 0:
        return np.zeros(0)
    with np.errstate(all="ignore"):
        first = np.zeros(npoint, bool)
        first[b.offsets[:-1][b.offsets[:-1] < npoint]] = True
        T = np.concatenate([b.times[:1], b.steps])
        T[first] = b.times[first]
        ignore = skip[owner] | (first & ~(T > 0))  # a first point at time 0 is dropped at the start
        if step_points:  # each point is commanded as given (the bound grows with each value)
            if bound(*largest) < MAX_COMMAND:
                return np.zeros(npoint)
            reach = bound(*(_magnitude(points) if magnitude is None else magnitude))
            reach[ignore] = 0.0
            return reach
        # the end values bound a Hermite segment's position, velocity and acceleration:
        # |basis| <= 1, its derivatives <= ~6 / T^k; 100 leaves room for the cubic's own a.
        # First the whole batch at once, from its largest values and longest and shortest segments
        used = T[~ignore]
        longest, shortest = used.max(initial=1.0), used[used > 0].min(initial=1.0)
        Mp, Mv, Ma = largest
        whole = 100.0 * bound(
            Mp + Mv * longest + Ma * longest**2,
            Mp / shortest + Mv + Ma * longest,
            Mp / shortest**2 + Mv / shortest + Ma,
        )
        if whole < MAX_COMMAND:
            return np.zeros(npoint)
        m = _magnitude(points) if magnitude is None else magnitude
        Mp, Mv, Ma = np.maximum(
            m, np.where(first, 0.0, np.concatenate([np.zeros((3, 1)), m[:, :-1]], axis=1))
        )
        safe = np.where(T > 0, T, 1.0)
        reach = 100.0 * bound(
            Mp + Mv * safe + Ma * safe**2, Mp / safe + Mv + Ma * safe, Mp / safe**2 + Mv / safe + Ma
        )
        reach[ignore] = 0.0
        close = np.flatnonzero(~(reach < MAX_COMMAND))
        if close.size:  # the polynomial's own bound, sum |c_k| s^k over the segment
            start = first[close][:, None]
            before = np.maximum(close - 1, 0)
            given = [np.zeros_like(p) if x is None else x for x in points]
            ends = np.stack(  # splines.ENDS: p0, p1, v0, v1, a0, a1
                [y for x in given for y in (np.where(start, 0.0, x[before]), x[close])]
            )
            c = coefficients(spline[owner[close]], ends, safe[close])
            powers = safe[close][:, None] ** np.arange(6)[:, None, None]  # (6, n, 1)
            mag = np.abs(c)  # (6, n, nj)
            position = (mag * powers).sum(axis=0)
            velocity = (mag[1:] * np.arange(1, 6)[:, None, None] * powers[:5]).sum(axis=0)
            acceleration = (mag[2:] * np.array([2, 6, 12, 20])[:, None, None] * powers[:4]).sum(axis=0)
            reach[close] = bound(position, velocity, acceleration).max(axis=1)
    return reach
