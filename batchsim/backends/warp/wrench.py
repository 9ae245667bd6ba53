"""External wrenches on MuJoCo Warp (batchsim.external_wrench), mixed into WarpSystem: write()
stages every wrenched world's xfrc_applied rows into a pinned host image of the whole array, and
one copy of it is queued on the device ahead of the next period's graph, which reads
`d.xfrc_applied` in place (a captured graph keeps the array's pointer). Nothing is allocated
before the first wrench.
"""

from __future__ import annotations

import numpy as np
import warp as wp


class WarpWrenches:
    """`_stage_xfrc` for WarpSystem, whose `nworld`, `model`, `device`, `_d` and `_host_array` it uses."""

    _xfrc_wp: wp.array | None = None  # (nworld, nbody) spatial_vector, pinned on a GPU
    _xfrc_host: np.ndarray | None = None  # its (nworld, nbody, 6) float32 view

    def _stage_xfrc(self, worlds: np.ndarray, xfrc: np.ndarray) -> None:
        if self._xfrc_wp is None:
            self._xfrc_wp = self._host_array((self.nworld, self.model.nbody), wp.spatial_vector)  # type: ignore[attr-defined]
            self._xfrc_host = self._xfrc_wp.numpy()
        self._xfrc_host[worlds] = xfrc
        with wp.ScopedDevice(self.device):  # type: ignore[attr-defined]
            wp.copy(self._d.xfrc_applied, self._xfrc_wp)  # type: ignore[attr-defined]
