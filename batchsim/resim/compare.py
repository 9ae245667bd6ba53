"""A re-run measured against the recording: each recorded joint state of a world (position and
velocity of every hinge and slide joint) beside the re-run's state at the same period's start
(joint_states are published from the state a period starts with). Bit-exact, or where and when
they part, and how long the re-run stays within a tolerance of the recording (its horizon)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import mujoco
import numpy as np

from batchsim.model.frames import frame_tree, relative_transforms
from batchsim.resim.physics import Trajectory
from batchsim.resim.recorded import JointStates, TfStates
from batchsim.stamps import stamps_ns

_MOVING = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))


@dataclasses.dataclass
class Comparison:
    """One world's re-run against its recording.

    Attributes:
      world: its number. compared: joint_states messages compared (of every robot's topic).
      joints: their joint names.
      exact: every compared value equal to the bit.
      max_position, max_velocity, max_effort: the largest difference (rad or m; rad/s or m/s;
        N m or N). Effort is compared where the recording says where it was read from, from
        the period after each (re)start (the system shows its reset's, or the step before the
        recording began); `efforts`: how many effort values were compared.
      first: where they first part at all: (sim time, period number, joint, |difference|), or
        None; the joint is named "<joint> (effort)" where its effort parts first.
      horizon: sim seconds from the world's (re)start until a position or velocity difference
        first exceeds `tolerance` (None: never, within the recording); `tolerance` as given.
      time, error: (n,) the compared messages' sim times and their largest position or velocity difference.
      skipped: joint_states names that are no hinge or slide joint of the model (not compared).
    """

    world: int
    compared: int
    joints: list[str]
    exact: bool
    max_position: float
    max_velocity: float
    first: tuple[float, int, str, float] | None
    horizon: float | None
    tolerance: float
    time: np.ndarray
    error: np.ndarray
    skipped: list[str]
    max_effort: float = 0.0
    efforts: int = 0

    def line(self) -> str:
        """One line for the terminal."""
        head = f"world {self.world}: {self.compared} joint_states compared"
        if not self.compared:
            return f"{head}: none (not recorded, or the world never ran)"
        what = "position, velocity and effort" if self.efforts else "position and velocity"
        if self.exact:
            return f"{head}: bit-exact (every {what} of {len(self.joints)} joints equal to the bit)"
        t, period, joint, diff = self.first
        horizon = "the whole recording" if self.horizon is None else f"{self.horizon:.3f} s"
        effort = f", {self.max_effort:.3g} (effort)" if self.efforts else ""
        return (
            f"{head}: they part at t={t:.3f} s (period {period}), {joint} first ({diff:.3g}); largest difference "
            f"{self.max_position:.3g} (position), {self.max_velocity:.3g} (velocity){effort}; within {self.tolerance:g} "
            f"for {horizon}"
        )

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["time"], d["error"] = self.time.tolist(), self.error.tolist()
        return d


def compare(
    model: mujoco.MjModel, world: int, run: Trajectory, headers: np.ndarray, states: Sequence[JointStates], tolerance: float
) -> Comparison:
    """Measure `run` (physics.rerun of `world`, or the controllers' re-run) against its recorded
    joint `states` (one per joint_states topic: a world of several robots has one per robot);
    effort too, for the joints whose effort the re-run knows (`run.effort`)."""
    empty = np.zeros(0)
    if not states:
        return Comparison(world, 0, [], False, np.nan, np.nan, None, None, tolerance, empty, empty, [])
    ran = ~np.isnan(run.qpos[:, 0]) if model.nq else np.ones(len(headers), bool)
    joints, skipped, compared, efforts = [], [], 0, 0
    error = np.full(len(headers), np.nan)  # per period, the largest difference of any topic compared in it
    max_position = max_velocity = max_effort = 0.0
    firsts = []  # per topic where it first parts: (period row, joint, |difference|)
    for topic in states:
        names, qadr, vadr, columns = [], [], [], []
        for c, name in enumerate(topic.names):
            j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
            if j < 0 or int(model.jnt_type[j]) not in _MOVING:
                skipped.append(name)
                continue
            names.append(name)
            columns.append(c)
            qadr.append(model.jnt_qposadr[j])
            vadr.append(model.jnt_dofadr[j])
        joints += names
        rows, at = _matched(headers, topic.stamps, ran)
        compared += len(rows)
        dpos = np.abs(topic.position[np.ix_(rows, columns)] - run.qpos[np.ix_(at, qadr)])
        dvel = np.abs(topic.velocity[np.ix_(rows, columns)] - run.qvel[np.ix_(at, vadr)])
        if not dpos.size:
            error[at] = np.fmax(error[at], 0.0)
            continue
        worst = np.maximum(dpos, np.nan_to_num(dvel))
        error[at] = np.fmax(error[at], worst.max(axis=1))
        max_position, max_velocity = max(max_position, float(dpos.max())), max(max_velocity, float(np.nanmax(dvel)))
        parted = np.flatnonzero(worst.max(axis=1) > 0)
        if parted.size:
            i = parted[0]
            j = int(np.argmax(worst[i]))
            firsts.append((int(at[i]), names[j], float(worst[i, j])))
        deff = _effort_differences(run, topic, rows, at, names, columns)
        if deff is not None:
            efforts += int(np.count_nonzero(~np.isnan(deff)))
            deff = np.nan_to_num(deff)
            max_effort = max(max_effort, float(deff.max()))
            parted = np.flatnonzero(deff.max(axis=1) > 0)
            if parted.size:
                i = parted[0]
                j = int(np.argmax(deff[i]))
                firsts.append((int(at[i]), f"{names[j]} (effort)", float(deff[i, j])))
    compared_at = np.flatnonzero(~np.isnan(error))
    time, step_error = headers[compared_at, 1], error[compared_at]
    first = None
    if firsts:
        k, joint, diff = min(firsts, key=lambda f: f[0])
        first = (float(headers[k, 1]), int(headers[k, 0]), joint, diff)
    beyond = np.flatnonzero(step_error > tolerance)
    horizon = float(time[beyond[0]] - run.since[compared_at[beyond[0]]]) if beyond.size else None
    return Comparison(
        world=world, compared=compared, joints=joints, exact=compared > 0 and first is None,
        max_position=max_position, max_velocity=max_velocity, first=first, horizon=horizon, tolerance=tolerance,
        time=time, error=step_error, skipped=skipped, max_effort=max_effort, efforts=efforts,
    )  # fmt: skip


def _effort_differences(
    run: Trajectory, topic: JointStates, rows: np.ndarray, at: np.ndarray, names: list[str], columns: list[int]
) -> np.ndarray | None:
    """(len(rows), len(names)) |recorded - re-run| effort, NaN where either is unknown (a joint
    whose source the recording does not say, a (re)start's period); None: nothing to compare."""
    if not run.effort or topic.effort is None:
        return None
    ours = np.full((len(at), len(names)), np.nan)
    for j, name in enumerate(names):
        series = run.effort.get(name)
        if series is not None:
            ours[:, j] = series[at]
    if np.isnan(ours).all():
        return None
    return np.abs(topic.effort[np.ix_(rows, columns)] - ours)


def _matched(headers: np.ndarray, stamps: np.ndarray, ran: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The recorded messages (`stamps`, ns) stamped with a period's start where the re-run ran
    (`ran`, (nperiod,) bool): (their rows, their periods' rows in `headers`)."""
    periods = stamps_ns(headers[:, 1])
    at = np.searchsorted(periods, stamps)
    found = (at < len(periods)) & (periods[np.minimum(at, len(periods) - 1)] == stamps)
    rows, at = np.flatnonzero(found), at[found]
    keep = ran[at]
    return rows[keep], at[keep]


@dataclasses.dataclass
class TfComparison:
    """A world's re-run body poses against its recorded /tf: `compared` messages, `exact`, the
    `largest` difference (m or unit quaternion), and where they first part: (sim time, frame,
    |difference|), or None; `unknown`: recorded frames the model has no body for."""

    compared: int
    exact: bool
    largest: float
    first: tuple[float, str, float] | None
    unknown: list[str]

    def line(self, world: int) -> str:
        head = f"world {world}: {self.compared} /tf messages compared"
        if not self.compared:
            return f"{head}: none"
        if self.exact:
            return f"{head}: bit-exact"
        t, frame, diff = self.first
        return f"{head}: they part at t={t:.3f} s, {frame} first ({diff:.3g}); largest difference {self.largest:.3g}"


def compare_tf(model: mujoco.MjModel, run: Trajectory, headers: np.ndarray, tf: TfStates | None) -> TfComparison:
    """The moving transforms the re-run's body poses make (batchsim.model.frames, as the bridge
    makes /tf) against the recorded ones, at every recorded stamp where the re-run knows them."""
    if tf is None or run.xpos is None:
        return TfComparison(0, False, 0.0, None, [])
    tree = frame_tree(model)
    index = {name: k for k, name in enumerate(tree.names)}
    known = [k for k, (_, child) in enumerate(tf.pairs) if child in index]
    unknown = [child for _, child in tf.pairs if child not in index]
    frames = np.array([index[tf.pairs[k][1]] for k in known], np.intp)
    rows, at = _matched(headers, tf.stamps, ~np.isnan(run.xpos[:, 0, 0]))
    t, r = relative_transforms(tree, run.xpos[at], run.xquat[at])
    ours = np.concatenate([t[:, frames], r[:, frames]], axis=2)
    diff = np.abs(ours - tf.values[rows][:, known])
    worst = diff.max(axis=2) if diff.size else np.zeros((len(rows), len(known)))
    parted = np.argwhere(worst > 0)
    first = None
    if parted.size:
        i, j = parted[0]
        first = (float(headers[at[i], 1]), tf.pairs[known[j]][1], float(worst[i, j]))
    return TfComparison(len(rows), len(rows) > 0 and first is None, float(worst.max()) if worst.size else 0.0, first, unknown)


def compare_series(
    what: str, world: int, headers: np.ndarray, ours: np.ndarray, recorded: tuple[np.ndarray, np.ndarray] | None
) -> str:
    """One line: the re-run's per-period values `ours` (nperiod, k; NaN rows not run) against a
    recorded series (stamps ns, (n, k)) of topic `what`: bit-exact, or where they first part."""
    if recorded is None:
        return f"world {world}: {what} not recorded"
    stamps, values = recorded
    rows, at = _matched(headers, stamps, ~np.isnan(ours[:, 0]))
    diff = np.abs(ours[at] - values[rows])
    head = f"world {world}: {len(rows)} {what} messages compared"
    if not len(rows):
        return f"{head}: none"
    parted = np.flatnonzero(diff.max(axis=1) > 0)
    if not parted.size:
        return f"{head}: bit-exact"
    i = parted[0]
    return f"{head}: they part at t={headers[at[i], 1]:.3f} s ({diff[i].max():.3g}); largest difference {diff.max():.3g}"
