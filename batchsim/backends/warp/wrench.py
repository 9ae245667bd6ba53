"""External wrenches on MuJoCo Warp (batchsim.plugins.external_wrench), `Wrenches`: write() stages
every wrenched world's xfrc_applied rows into a pinned host image of the whole array, and one
copy of it is queued on the device ahead of the next period's graph, which reads
`d.xfrc_applied` in place (a captured graph keeps the array's pointer). Nothing is allocated
before the first wrench.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from batchsim.backends.warp.host import host_array
from batchsim.backends.warp.worlds import DeviceWorlds


class Wrenches:
    """The engine's `stage_xfrc`."""

    def __init__(self, worlds: DeviceWorlds):
        self._worlds = worlds
        self._image: wp.array | None = None  # (nworld, nbody) spatial_vector, pinned on a GPU
        self._rows: np.ndarray | None = None  # its (nworld, nbody, 6) float32 view

    def stage(self, worlds: np.ndarray, xfrc: np.ndarray) -> None:
        """xfrc_applied of `worlds` `(k,)` = `xfrc` `(k, nbody, 6)`, the others' as they were."""
        w = self._worlds
        if self._image is None:
            self._image = host_array((w.nworld, w.model.nbody), wp.spatial_vector, w.cuda)
            self._rows = self._image.numpy()
        self._rows[worlds] = xfrc
        with wp.ScopedDevice(w.device):
            wp.copy(w.d.xfrc_applied, self._image)
