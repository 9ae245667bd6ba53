"""Body poses on MuJoCo Warp (`Poses`: the engine's `body_poses` and `pose_rows`): `xpos` and
`xquat` of some worlds gathered on the device and copied down in one piece, or every world's
(tf asks each period) copied into pinned host arrays kept for it: no gather, no allocation.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from batchsim.backends.warp.host import host_array
from batchsim.backends.warp.kernels import gather_poses
from batchsim.backends.warp.worlds import DeviceWorlds


class Poses:
    """Every body's pose in the engine's worlds, for the host."""

    def __init__(self, worlds: DeviceWorlds):
        self._worlds = worlds
        self._rows: tuple[wp.array, wp.array] | None = None  # pinned xpos, xquat of every world (a GPU)

    def of(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """xpos (n, nbody, 3) and xquat (n, nbody, 4) float32 of `worlds`, host arrays of the caller's."""
        w = self._worlds
        nbody = w.model.nbody
        # gathered on the device, then one copy of just those worlds to the host
        with wp.ScopedDevice(w.device):
            index = wp.array(worlds.astype(np.int32), dtype=wp.int32)
            poses = wp.empty((len(worlds), nbody, 7), dtype=wp.float32)
            if len(worlds):
                wp.launch(
                    gather_poses,
                    dim=(len(worlds), nbody),
                    inputs=[index, w.d.xpos, w.d.xquat],
                    outputs=[poses],
                    device=w.device,
                )
            host = poses.numpy()
        return host[..., :3], host[..., 3:]

    def rows(self) -> tuple[np.ndarray, np.ndarray]:
        """Every world's xpos and xquat, float32: the engine's own arrays on Warp's CPU device, else
        one copy of each into the pinned host arrays kept for it."""
        w = self._worlds
        d = w.d
        if not w.cuda:
            return d.xpos.numpy(), d.xquat.numpy()
        with wp.ScopedDevice(w.device):
            if self._rows is None:
                self._rows = (host_array(d.xpos.shape, wp.vec3, True), host_array(d.xquat.shape, wp.quat, True))
            wp.copy(self._rows[0], d.xpos)
            wp.copy(self._rows[1], d.xquat)
            wp.synchronize_device(w.device)
        return self._rows[0].numpy(), self._rows[1].numpy()
