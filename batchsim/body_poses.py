"""Every body's pose in the world frame (tf's source): `body_poses(worlds=None)`, arrays of the
caller's own, and `body_poses_into(xpos_out, xquat_out, bodies)`, what tf copies every control
period: the listed bodies of every world straight into the caller's buffers. Mixed into BatchedSystem; the engine
hooks are `_body_poses` and `_pose_rows` (batchsim.engine).

A frozen world shows the poses the last call gave it before it froze. Where the engine's rows
hold them already (`_pose_rows_hold_frozen`: a fleet over devices, whose shards each keep their
own), nothing more is copied; else every call keeps what it gave, to show once a world freezes.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import mujoco
import numpy as np

from batchsim.lifecycle import LifecycleState

_RUNNING = frozenset({LifecycleState.INACTIVE, LifecycleState.ACTIVE})


class BodyPoses:
    """body_poses() and body_poses_into() of the contract (batchsim.hardware)."""

    #: whether `_pose_rows()` already shows frozen worlds' held poses
    _pose_rows_hold_frozen: bool = False
    _shown_poses: tuple[np.ndarray, np.ndarray] | None = None  # the last poses each world was given

    def body_poses(self, worlds: Sequence[int] | np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Every body's pose in the world frame, in all or the listed worlds (indices, in the order
        given, or a bool mask): positions `(n, nbody, 3)` and orientation quaternions
        `(n, nbody, 4)` (w, x, y, z), float64 arrays of the caller's own; body 0 is the world body.

        They are MuJoCo's `xpos`/`xquat` as the engine computed them in its last step, i.e. the
        kinematics of the state before the last physics substep, like `sensordata`; after
        reset(), of the reset state. A frozen world shows the poses the last call gave it before
        it froze (the initial state's, if no call did). Nothing is fetched or computed until
        the first call (batchsim.model.frames turns them into tf transforms).
        """
        self._require("read body poses", _RUNNING)  # type: ignore[attr-defined]
        rows = self._worlds(worlds)  # type: ignore[attr-defined]
        source = self._pose_rows() if rows is None else None
        if source is not None:  # every world, as the engine's host rows hold them: one copy
            xpos, xquat = (np.array(a, dtype=np.float64) for a in source)
            if not self._pose_rows_hold_frozen:
                self._show(None, xpos, xquat)
            return xpos, xquat
        sel = np.arange(self.nworld) if rows is None else rows  # type: ignore[attr-defined]
        xpos, xquat = self._body_poses(sel)  # type: ignore[attr-defined]
        xpos, xquat = xpos.astype(np.float64, copy=False), xquat.astype(np.float64, copy=False)
        self._show(None if rows is None else sel, xpos, xquat)
        return xpos, xquat

    def body_poses_into(
        self, xpos_out: np.ndarray, xquat_out: np.ndarray, bodies: Sequence[int] | np.ndarray | slice = slice(None)
    ) -> None:
        """Every world's poses of `bodies` (default all) into `xpos_out` `(nworld, nb, 3)` and
        `xquat_out` `(nworld, nb, 4)` (views will do: tf's channel holds both side by side), as
        body_poses() gives them. What tf copies each control period: one pass over the bodies
        asked for from the engine's host rows where it keeps them, no arrays of every body between."""
        self._require("read body poses", _RUNNING)  # type: ignore[attr-defined]
        pick = _as_slice(bodies)
        source = self._pose_rows()
        if source is None:  # the engine has no host rows: its gather, as body_poses() does it
            xpos, xquat = self.body_poses()
        else:
            xpos, xquat = source
            if not self._pose_rows_hold_frozen:
                xpos, xquat = self._show_rows(xpos, xquat)
        xpos_out[...] = xpos[:, pick]
        xquat_out[...] = xquat[:, pick]

    # --- what a frozen world goes on showing ---
    def _shown(self) -> tuple[np.ndarray, np.ndarray]:
        if self._shown_poses is None:  # the initial state's, until a call gives more
            model: Any = self.model  # type: ignore[attr-defined]
            mjd = mujoco.MjData(model)
            self.spec.initial.apply(model, mjd)  # type: ignore[attr-defined]
            n = self.nworld  # type: ignore[attr-defined]
            self._shown_poses = (np.tile(mjd.xpos, (n, 1, 1)), np.tile(mjd.xquat, (n, 1, 1)))
        return self._shown_poses

    def _show(self, sel: np.ndarray | None, xpos: np.ndarray, xquat: np.ndarray) -> None:
        """Frozen worlds' rows of `xpos`/`xquat` (worlds `sel`, None: all) replaced by what they
        showed; the others' kept to show once they freeze."""
        frozen = self.frozen if sel is None else self.frozen[sel]  # type: ignore[attr-defined]
        for shown, now in zip(self._shown(), (xpos, xquat), strict=True):
            if frozen.any():
                now[frozen] = shown[frozen if sel is None else sel[frozen]]
            if sel is None:
                np.copyto(shown, now)
            else:
                shown[sel] = now

    def _show_rows(self, xpos: np.ndarray, xquat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The engine's rows (not ours to change) with frozen worlds' held poses: the unfrozen
        worlds' kept to show once they freeze; the shown arrays where a world is frozen."""
        frozen = self.frozen  # type: ignore[attr-defined]
        live = None if not frozen.any() else ~frozen[:, None, None]
        for shown, now in zip(self._shown(), (xpos, xquat), strict=True):
            np.copyto(shown, now, where=True if live is None else live)
        return (xpos, xquat) if live is None else self._shown()

def _as_slice(bodies: Sequence[int] | np.ndarray | slice) -> slice | np.ndarray:
    """`bodies` as a slice where they are consecutive (a view, no gather), else an index array."""
    if isinstance(bodies, slice):
        return bodies
    index = np.asarray(bodies, dtype=np.intp).reshape(-1)
    if index.size and np.array_equal(index, np.arange(index[0], index[0] + index.size)):
        return slice(int(index[0]), int(index[0]) + index.size)
    return index
