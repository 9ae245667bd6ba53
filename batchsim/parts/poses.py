"""Every body's pose in the world frame (tf's source), a part of the system: `body_poses(worlds)`,
arrays of the caller's own, and `body_poses_into(xpos_out, xquat_out, bodies)`, what tf copies
every control period: the listed bodies of every world straight into the caller's buffers.

A frozen world shows the poses the last call gave it before it froze. Where the source's rows
hold them already (`hold_frozen`: a fleet over devices, whose shards each keep their own),
nothing more is copied; else every call keeps what it gave, to show once a world freezes.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol

import mujoco
import numpy as np

from batchsim.model import RobotSpec
from batchsim.types import as_slice


class PoseSource(Protocol):
    """Where poses come from: the engine's `body_poses` and `pose_rows` (batchsim.engine)."""

    def body_poses(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...
    def pose_rows(self) -> tuple[np.ndarray, np.ndarray] | None: ...


class BodyPoses:
    """The poses of `nworld` worlds of `spec` from `source`; `frozen()` gives the worlds that show
    what they showed before they froze (`hold_frozen`: the source's rows show that already)."""

    def __init__(
        self,
        spec: RobotSpec,
        nworld: int,
        source: PoseSource,
        frozen: Callable[[], np.ndarray],
        *,
        hold_frozen: bool = False,
    ):
        self.spec, self.nworld = spec, nworld
        self._source = source
        self._frozen = frozen
        self._hold_frozen = hold_frozen
        self._shown_poses: tuple[np.ndarray, np.ndarray] | None = None  # the last poses each world was given

    def body_poses(self, rows: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Positions `(n, nbody, 3)` and orientation quaternions `(n, nbody, 4)` (w, x, y, z) of
        worlds `rows` (None: all), float64 arrays of the caller's own (the contract's
        `body_poses` says what they are)."""
        source = self._source.pose_rows() if rows is None else None
        if source is not None:  # every world, as the source's host rows hold them: one copy
            xpos, xquat = (np.array(a, dtype=np.float64) for a in source)
            if not self._hold_frozen:
                self._show(None, xpos, xquat)
            return xpos, xquat
        sel = np.arange(self.nworld) if rows is None else rows
        xpos, xquat = self._source.body_poses(sel)
        xpos, xquat = xpos.astype(np.float64, copy=False), xquat.astype(np.float64, copy=False)
        self._show(None if rows is None else sel, xpos, xquat)
        return xpos, xquat

    def body_poses_into(
        self, xpos_out: np.ndarray, xquat_out: np.ndarray, bodies: Sequence[int] | np.ndarray | slice = slice(None)
    ) -> None:
        """Every world's poses of `bodies` into `xpos_out` `(nworld, nb, 3)` and `xquat_out`
        `(nworld, nb, 4)`: one pass over the bodies asked for from the source's host rows where
        it keeps them, no arrays of every body between."""
        pick = bodies if isinstance(bodies, slice) else as_slice(bodies)  # a view where it can
        source = self._source.pose_rows()
        if source is None:  # the source has no host rows: its gather, as body_poses() does it
            xpos, xquat = self.body_poses(None)
        else:
            xpos, xquat = source
            if not self._hold_frozen:
                xpos, xquat = self._show_rows(xpos, xquat)
        xpos_out[...] = xpos[:, pick]
        xquat_out[...] = xquat[:, pick]

    # --- what a frozen world goes on showing ---
    def _shown(self) -> tuple[np.ndarray, np.ndarray]:
        if self._shown_poses is None:  # the initial state's, until a call gives more
            model = self.spec.mjmodel
            mjd = mujoco.MjData(model)
            self.spec.initial.apply(model, mjd)
            n = self.nworld
            self._shown_poses = (np.tile(mjd.xpos, (n, 1, 1)), np.tile(mjd.xquat, (n, 1, 1)))
        return self._shown_poses

    def _show(self, sel: np.ndarray | None, xpos: np.ndarray, xquat: np.ndarray) -> None:
        """Frozen worlds' rows of `xpos`/`xquat` (worlds `sel`, None: all) replaced by what they
        showed; the others' kept to show once they freeze."""
        frozen = self._frozen() if sel is None else self._frozen()[sel]
        for shown, now in zip(self._shown(), (xpos, xquat), strict=True):
            if frozen.any():
                now[frozen] = shown[frozen if sel is None else sel[frozen]]
            if sel is None:
                np.copyto(shown, now)
            else:
                shown[sel] = now

    def _show_rows(self, xpos: np.ndarray, xquat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The source's rows (not ours to change) with frozen worlds' held poses: the unfrozen
        worlds' kept to show once they freeze; the shown arrays where a world is frozen."""
        frozen = self._frozen()
        live = None if not frozen.any() else ~frozen[:, None, None]
        for shown, now in zip(self._shown(), (xpos, xquat), strict=True):
            np.copyto(shown, now, where=True if live is None else live)
        return (xpos, xquat) if live is None else self._shown()

