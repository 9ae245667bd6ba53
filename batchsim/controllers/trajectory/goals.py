"""Action goals of the trajectory controller: tolerances and outcomes, over every world.

What ros2_controllers' JointTrajectoryController does for a FollowJointTrajectory goal
(`tolerances.hpp` and the goal checks of its `update`), vectorized over worlds; the ROS
bridge serves the action and reads the outcomes.

- Defaults come from the YAML's `constraints` block: `stopped_velocity_tolerance` (0.01)
  is every joint's goal velocity tolerance, `goal_time` (0) the goal time tolerance,
  `<joint>.trajectory` (0) its path position tolerance, `<joint>.goal` (0) its goal
  position tolerance. A tolerance of 0 is no check.
- A goal's own tolerances override them per joint and per variable (position, velocity,
  acceleration) as control_msgs/JointTolerance says: 0 (or NaN here: a joint the goal
  leaves out) keeps the default, -1 erases it (no check), a positive value replaces it.
  Any other negative value is illegal, and the goal then takes every default, as upstream.
- Errors are reference minus measured state, sampled each update. As upstream computes
  them, the velocity error counts only with a velocity state interface and a velocity or
  effort command interface, the acceleration error only with acceleration state and
  command interfaces; otherwise those tolerances never fail.
- While the trajectory runs (and on its first sample) the path tolerances are checked:
  outside -> PATH_TOLERANCE_VIOLATED. Once past the last point: inside the goal tolerances
  -> SUCCEEDED; outside with a goal time tolerance > 0 and more than that past the last
  point -> GOAL_TOLERANCE_VIOLATED; otherwise the goal stays ACTIVE (with a goal time
  tolerance of 0, until the world gets inside or the goal is replaced, as upstream waits
  "a potentially infinite amount of time"). The controller holds a violating world where
  it is measured to be.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from batchsim.controllers.base import Params, rows_any
from batchsim.controllers.topics import GoalOutcome

#: control_msgs/JointTolerance's value that erases a default tolerance
ERASE = -1.0
_ERASE_EPSILON = float(np.finfo(np.float32).eps)  # as upstream compares it


@dataclasses.dataclass(frozen=True)
class Constraints:
    """The controller's `constraints` parameters, as upstream declares them.

    Attributes:
      stopped_velocity_tolerance: every joint's goal velocity tolerance (default 0.01).
      goal_time: the goal time tolerance, seconds (default 0: wait for the goal tolerance).
      trajectory: (njoint,) path position tolerances, `constraints.<joint>.trajectory` (0: none).
      goal: (njoint,) goal position tolerances, `constraints.<joint>.goal` (0: none).
      decelerate_on_cancel, max_deceleration_on_cancel: (njoint,) accepted, not acted on:
        a canceled or violating world holds where it is.
    """

    stopped_velocity_tolerance: float
    goal_time: float
    trajectory: np.ndarray
    goal: np.ndarray
    decelerate_on_cancel: bool
    max_deceleration_on_cancel: np.ndarray

    @classmethod
    def read(cls, params: Params, joints: Sequence[str]) -> Constraints:
        """From `params`; a key under `constraints` not read here is left for `Params.unused`."""

        def joint_values(key: str) -> np.ndarray:
            return np.array([params.number(f"constraints.{j}.{key}", 0.0, minimum=0.0) for j in joints])

        return cls(
            stopped_velocity_tolerance=params.number("constraints.stopped_velocity_tolerance", 0.01),
            goal_time=params.number("constraints.goal_time", 0.0, minimum=0.0),
            trajectory=joint_values("trajectory"),
            goal=joint_values("goal"),
            decelerate_on_cancel=params.boolean("constraints.decelerate_on_cancel", False),
            max_deceleration_on_cancel=joint_values("max_deceleration_on_cancel"),
        )

    def path_tolerance(self) -> np.ndarray:
        """(njoint, 3) the default path tolerance: position, velocity, acceleration."""
        tolerance = np.zeros((len(self.trajectory), 3))
        tolerance[:, 0] = self.trajectory
        return tolerance

    def goal_tolerance(self) -> np.ndarray:
        """(njoint, 3) the default goal tolerance."""
        tolerance = np.zeros((len(self.goal), 3))
        tolerance[:, 0] = self.goal
        tolerance[:, 1] = self.stopped_velocity_tolerance
        return tolerance


def resolve(default: np.ndarray, given: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Goal tolerances over defaults, with control_msgs/JointTolerance's special values.

    Args:
      default: (...) the default of each value (broadcast against `given`).
      given: (n, ...) the goals' values: > 0 replaces, 0 or NaN keeps the default, -1 erases
        (0: no check); None: every goal keeps the defaults.

    Returns:
      (n, ...) the resolved values, and (n,) bool: the goals with an illegal (other
      negative) value, whose values here are meaningless (upstream takes every default).
    """
    if given is None:
        return np.asarray(default), np.zeros(0, bool)
    erase = np.abs(given - ERASE) < _ERASE_EPSILON
    out = np.where(given > 0, given, np.where(erase, 0.0, default))
    illegal = (given < 0) & ~erase
    return out, illegal.reshape(len(given), -1).any(axis=1)


def limits(tolerance: np.ndarray) -> np.ndarray:
    """(3, n, njoint): tolerances (n, njoint, 3) as the limits `outside` compares against,
    variable first (contiguous per variable) and +inf where 0 means no check."""
    return np.where(tolerance > 0, tolerance, np.inf).transpose(2, 0, 1)


def outside(limit: np.ndarray, errors: Sequence[np.ndarray | None]) -> np.ndarray:
    """(n, njoint) bool: joints whose |error| exceeds its limit.

    Args:
      limit: (3, n, njoint) position, velocity, acceleration limits, +inf for none (`limits`).
      errors: (position, velocity, acceleration) errors, each (n, njoint) or None (not checked).
    """
    bad = np.zeros(limit.shape[1:], bool)
    for k, error in enumerate(errors):
        if error is not None:
            bad |= np.abs(error) > limit[k]
    return bad


class GoalTracker:
    """Every world's goal: its tag, its tolerances, and its outcome.

    A world follows at most one goal: the newest trajectory queued for it, if that came
    with a tag. Its checks start when its trajectory starts (not while it waits for its
    start time) and end with its outcome.

    Attributes:
      goal: (nworld,) int64, the tag of the goal the world follows or last followed; 0 none.
      outcome: (nworld,) int8 GoalOutcome of that goal.
      outcome_joint: (nworld,) int64, the joint (controller order) that violated a
        tolerance; -1 otherwise.
    """

    def __init__(self, nworld: int, constraints: Constraints):
        nj = len(constraints.goal)
        # each world's defaults, (nworld, njoint, 3) and (nworld,): set_defaults changes a world's
        self.default_path = np.repeat(constraints.path_tolerance()[None], nworld, axis=0)
        self.default_goal = np.repeat(constraints.goal_tolerance()[None], nworld, axis=0)
        self.default_goal_time = np.full(nworld, constraints.goal_time)
        self.goal = np.zeros(nworld, np.int64)
        self.outcome = np.zeros(nworld, np.int8)
        self.outcome_joint = np.full(nworld, -1, np.int64)
        # the goal's resolved tolerances, as limits (3, nworld, njoint): see `limits`
        self._path = np.full((3, nworld, nj), np.inf)
        self._goal = np.full((3, nworld, nj), np.inf)
        self._goal_time = np.zeros(nworld)
        self._end = np.zeros(nworld)  # sim time of the goal's last point
        self._queued = np.zeros(nworld, bool)  # the pending trajectory carries the world's goal
        self._checking = np.zeros(nworld, bool)  # its trajectory started: checks run
        self._first = np.zeros(nworld, bool)  # it started this update: the path check runs anyway

    def set_defaults(self, worlds: np.ndarray, constraints: Constraints) -> None:
        """The listed worlds' default tolerances become `constraints`' (its parameters set at run
        time): for the goals they queue from now on, as upstream's update takes changed
        parameters for the next goal; a goal already running keeps the tolerances it started with."""
        self.default_path[worlds] = constraints.path_tolerance()
        self.default_goal[worlds] = constraints.goal_tolerance()
        self.default_goal_time[worlds] = constraints.goal_time

    def queue(
        self,
        worlds: np.ndarray,
        tags: np.ndarray,
        path: np.ndarray | None,
        goal: np.ndarray | None,
        goal_time: np.ndarray | None,
    ) -> None:
        """Trajectories were queued for `worlds` (each once): each replaces the world's goal.

        Args:
          worlds: (n,) the worlds.
          tags: (n,) int64 each trajectory's goal tag; 0: a topic trajectory (no goal).
          path, goal: (n, njoint, 3) the goals' tolerances as sent (see `resolve`), or None.
          goal_time: (n,) the goals' goal time tolerances as sent, or None.
        """
        has = tags != 0
        self.goal[worlds] = tags
        self.outcome[worlds] = np.where(has, GoalOutcome.ACTIVE, GoalOutcome.NONE)
        self.outcome_joint[worlds] = -1
        self._queued[worlds] = has
        self._checking[worlds] = False
        if not has.any():
            return
        w = worlds[has]
        pick = lambda a: None if a is None else a[has]  # noqa: E731
        path_tol, bad_path = resolve(self.default_path[w], pick(path))
        goal_tol, bad_goal = resolve(self.default_goal[w], pick(goal))
        time_tol, bad_time = resolve(self.default_goal_time[w], pick(goal_time))
        self._path[:, w] = limits(path_tol)
        self._goal[:, w] = limits(goal_tol)
        self._goal_time[w] = time_tol
        illegal = np.zeros(len(w), bool)
        for bad in (bad_path, bad_goal, bad_time):
            if bad.size:
                illegal |= bad
        if illegal.any():  # upstream: an illegal value anywhere -> every default
            bad = w[illegal]
            self._path[:, bad] = limits(self.default_path[bad])
            self._goal[:, bad] = limits(self.default_goal[bad])
            self._goal_time[bad] = self.default_goal_time[bad]

    def start(self, worlds: np.ndarray, end: np.ndarray) -> None:
        """The queued trajectories of `worlds` started (or were all in the past); `end`:
        (n,) sim time of each one's last point."""
        mine = self._queued[worlds]
        if not mine.any():
            return
        w = worlds[mine]
        self._queued[w] = False
        self._checking[w] = True
        self._first[w] = True
        self._end[w] = end[mine]

    @property
    def checking(self) -> bool:
        """Some world has a started goal to check."""
        return bool(self._checking.any())

    def check(self, time: float, executing: np.ndarray, errors: Sequence[np.ndarray | None]) -> np.ndarray:
        """Check every started goal against its tolerances; returns the worlds to hold where
        they are (their goal was aborted for a violation).

        Args:
          time: sim time of this update.
          executing: (nworld,) bool, the world's trajectory is before its last point.
          errors: (position, velocity, acceleration), each (nworld, njoint) reference minus
            measured, or None where upstream does not compute it.
        """
        w = np.flatnonzero(self._checking)
        moving = executing[w]
        path_w = w[moving | self._first[w]]  # upstream checks the path on the first sample too
        goal_w = w[~moving]
        self._first[:] = False
        path_bad = self._outside(self._path, path_w, errors)
        path_rows = rows_any(path_bad)
        violated = path_w[path_rows]
        goal_bad = self._outside(self._goal, goal_w, errors)
        inside = ~rows_any(goal_bad)
        clear = ~np.isin(goal_w, violated) if violated.size else np.ones(len(goal_w), bool)
        succeeded = goal_w[inside & clear]
        late_rows = ~inside & clear
        if late_rows.any():  # past the goal time tolerance after the last point (0: wait)
            expired = (self._goal_time > 0) & (time - self._end > self._goal_time)
            late_rows &= expired[goal_w]
        late = goal_w[late_rows]
        if not (violated.size or succeeded.size or late.size):
            return violated
        self.outcome[succeeded] = GoalOutcome.SUCCEEDED
        self.outcome[violated] = GoalOutcome.PATH_TOLERANCE_VIOLATED
        self.outcome_joint[violated] = np.argmax(path_bad[path_rows], axis=1)
        self.outcome[late] = GoalOutcome.GOAL_TOLERANCE_VIOLATED
        self.outcome_joint[late] = np.argmax(goal_bad[late_rows], axis=1)
        ended = np.concatenate([violated, succeeded, late])
        self._checking[ended] = False
        return np.concatenate([violated, late])

    def _outside(
        self, tolerance: np.ndarray, worlds: np.ndarray, errors: Sequence[np.ndarray | None]
    ) -> np.ndarray:
        """outside() for `worlds`, through views when they are every world (the costly case)."""
        if not len(worlds):
            return np.zeros((0, tolerance.shape[2]), bool)
        rows = slice(None) if len(worlds) == tolerance.shape[1] else worlds
        return outside(tolerance[:, rows], [None if e is None else e[rows] for e in errors])

    def cancel(self, worlds: np.ndarray, tags: np.ndarray) -> np.ndarray:
        """Cancel the goals `tags` (n,) of `worlds` (n,) where still ACTIVE; returns the
        canceled worlds (to hold where they are)."""
        hit = (self.goal[worlds] == tags) & (self.outcome[worlds] == GoalOutcome.ACTIVE) & (tags != 0)
        w = np.unique(worlds[hit])
        self.outcome[w] = GoalOutcome.CANCELED
        self._end_checks(w)
        return w

    def abort(self, worlds: np.ndarray, outcome: GoalOutcome = GoalOutcome.ABORTED) -> None:
        """The worlds were reset (or their controller deactivated: DEACTIVATED): their ACTIVE
        goals end as `outcome`."""
        active = worlds[self.outcome[worlds] == GoalOutcome.ACTIVE]
        self.outcome[active] = outcome
        self._end_checks(worlds)

    def _end_checks(self, worlds: np.ndarray) -> None:
        self._checking[worlds] = False
        self._queued[worlds] = False
        self._first[worlds] = False
