"""The contract's cameras, lidars and sensor noise (batchsim.sensors), mixed into BatchedSystem:
the sensor suite and its configuration, `render`, `render_async` and `scan` over the camera and
lidar hooks (batchsim.engine), and the noise on read()'s values with the truth kept beside it
(`true_state`, `true_sensordata`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from batchsim.lifecycle import LifecycleState
from batchsim.sensors import Lidar, LidarKind, SensorConfig, SensorSuite
from batchsim.types import Frames, PendingFrames, SensorData

S = LifecycleState


class Sensing:
    """Cameras, lidars and sensor noise of `nworld` worlds. Mixed into BatchedSystem: it uses the
    system's `spec`, `nworld`, `state`, `sensordata`, `status`, `frozen`, the host arrays read()
    fills (`_readings`, `_sensor_host`), the lifecycle's `_require`, the world-list check
    `_worlds`, and the camera and lidar hooks.
    """

    @property
    def sensors(self) -> SensorSuite:
        """The cameras, lidars and sensor noise of every world, and which worlds want each."""
        if self._sensors is None:
            self._sensors = SensorSuite.build(self.spec, self.nworld, self._sensor_config)
        return self._sensors

    def set_sensor_config(self, config: SensorConfig | str | Path | Mapping[str, Any]) -> None:
        """Configure cameras, lidars and noise (batchsim.sensors.config: a SensorConfig, YAML file or
        mapping), before configure(). Raises SensorConfigError naming the file and key at fault."""
        self._require("set the sensor configuration", frozenset({S.UNKNOWN, S.UNCONFIGURED}))
        if not isinstance(config, SensorConfig):
            config = SensorConfig.load(config)
        self._sensors = SensorSuite.build(self.spec, self.nworld, config)
        self._sensor_config = config

    @property
    def true_state(self) -> np.ndarray:
        """(nworld, nstate) float64: `state` without sensor noise; `state` itself when there is none."""
        truth = self._truth()
        return self.state if truth is None else truth[0][:, : len(self.spec.state)]

    @property
    def true_sensordata(self) -> SensorData:
        """Every MJCF sensor by name without noise, (nworld, dim); `sensordata` when there is none."""
        truth = self._truth()
        if truth is None:
            return self.sensordata
        return SensorData(truth[1], self.spec.sensors)

    def _truth(self) -> tuple[np.ndarray, np.ndarray] | None:
        noise = self.sensors.reading_noise
        return None if noise is None else noise.truth

    def render(
        self, camera: str, worlds: Sequence[int] | np.ndarray | None = None, *, device: bool = False, copy: bool = True
    ) -> Frames:
        """Render `camera` in all or the listed worlds (indices or a bool mask), at the current state.

        Returns Frames(rgb (n, H, W, 3) uint8, depth (n, H, W) float32), row i for world
        `worlds[i]` in the order given (a bool mask lists worlds in order): top row first, depth
        in metres along the optical axis, +inf where nothing was hit, NaN where noise dropped a
        pixel. `device=True` returns the backend's own arrays for every world without a host
        copy or noise (Warp arrays on warp, JAX on mjx, NumPy on cpu); `copy=False` may return
        buffers the next render overwrites.
        """
        self._require("render", frozenset({S.INACTIVE, S.ACTIVE}))
        cam = self.sensors.camera(camera)
        if device:
            if worlds is not None:
                raise ValueError("render(device=True) renders every world: leave worlds=None and index on the device")
            return Frames(*self._device_frames(cam))
        rows = self._worlds(worlds)
        sel = np.arange(self.nworld) if rows is None else rows
        ascending, order = _ascending(sel)
        rgb, depth = self._render_frames(cam, ascending, copy)
        if order is not None:
            rgb, depth = rgb[order], depth[order]
        self.sensors.add_noise(cam.name, depth, sel)  # after the reordering: world w's noise on world w's row
        return Frames(rgb, depth)

    def render_async(self, camera: str, worlds: Sequence[int] | np.ndarray | None = None) -> PendingFrames:
        """Start rendering `camera` in all or the listed worlds at the current state; return at once.

        `result()` of the PendingFrames gives what `render(camera, worlds)` would have given
        now (host arrays of the caller's own, noise included), waiting if need be. cpu and mjx
        draw them on a background thread with its own OpenGL context, from a copy of the
        worlds' poses taken now, so the caller can step on meanwhile (SensorSampler does:
        the physics and the rendering then use two cores); the others render before
        returning. Renders run in the order they were asked for.
        """
        self._require("render", frozenset({S.INACTIVE, S.ACTIVE}))
        cam = self.sensors.camera(camera)
        rows = self._worlds(worlds)
        sel = np.arange(self.nworld) if rows is None else rows
        ascending, order = _ascending(sel)
        return PendingFrames(self._render_frames_later(cam, ascending), cam.name, sel, self.sensors, order)

    def prepare_rendering(self) -> None:
        """Set up now what the first `render_async` would otherwise set up inside the loop: on cpu
        and mjx the render thread and its OpenGL context (making one holds Python's GIL for
        ~0.2 s, a stalled control period if the loop runs). Nothing on warp, whose render
        context, holding every world's frames, is made on a camera's first render.
        SensorSampler calls it when it is made."""
        self._require("prepare rendering", frozenset({S.INACTIVE, S.ACTIVE}))
        if self.sensors.cameras:
            self._prepare_rendering(list(self.sensors.cameras.values()))

    def scan(
        self, lidar: str, worlds: Sequence[int] | np.ndarray | None = None, *, device: bool = False, copy: bool = True
    ) -> np.ndarray:
        """One scan of `lidar` in all or the listed worlds: (n, nray) float32 ranges in metres, REP 117
        (+inf: no hit within range_max, -inf: closer than range_min, NaN: dropped by noise), row i
        for world `worlds[i]` in the order given (a bool mask lists worlds in order).

        Rangefinder lidars read the MJCF rangefinders (as of the last step, like every
        sensor); the others cast their rays now, at the current state. `device=True` returns
        the backend's own (nworld, nray) array of every world without a host copy or noise
        (a Warp array on warp, JAX on mjx, NumPy on cpu), as `render(device=True)`;
        `copy=False` may return a buffer the next scan of this lidar overwrites.
        """
        self._require("scan", frozenset({S.INACTIVE, S.ACTIVE}))
        ld = self.sensors.lidar(lidar)
        if device:
            if worlds is not None:
                raise ValueError("scan(device=True) scans every world: leave worlds=None and index on the device")
            return self._device_ranges(ld)
        rows = self._worlds(worlds)
        sel = np.arange(self.nworld) if rows is None else rows
        ascending, order = _ascending(sel)
        ranges = self._ranges(ld, ascending, copy)
        if order is not None:
            ranges = ranges[order]
        self.sensors.add_noise(ld.name, ranges, sel)  # after the reordering: world w's noise on world w's row
        return ranges

    def _ranges(self, ld: Lidar, worlds: np.ndarray, copy: bool = True) -> np.ndarray:
        """Noise-free REP 117 ranges (n, nray) float32 of `ld` in `worlds` (a buffer if not `copy`)."""
        if ld.kind is LidarKind.RANGEFINDER:
            truth = self._truth()
            return ld.ranges((self._sensor_host if truth is None else truth[1])[np.ix_(worlds, ld.sensor_adr)])
        return self._cast_ranges(ld, worlds, copy)

    # --- noise on read()'s values ---
    def _add_noise(self) -> None:
        """Sensor noise on the refreshed host readings (read() and reset(), after `_refresh`),
        the truth kept for `true_state`; a frozen world keeps its noise-free held readings
        rather than fresh noise on every read."""
        noise = self.sensors.reading_noise
        if noise is None:
            return
        self.sensors.add_reading_noise(self._readings, self._sensor_host)
        if self.status.any():
            frozen = self.frozen
            if frozen.any():
                truth_readings, truth_sensordata = noise.truth
                self._readings[frozen] = truth_readings[frozen]
                self._sensor_host[frozen] = truth_sensordata[frozen]

    def _noise_free(self) -> tuple[np.ndarray, np.ndarray]:
        """The last read()'s readings `(nworld, ncolumn)` and sensordata `(nworld, nsensordata)`
        without sensor noise: the truth buffers, or the host arrays where there is no noise."""
        truth = self._truth()
        return (self._readings, self._sensor_host) if truth is None else truth


def _ascending(worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """`worlds` (unique) sorted, and the index that puts rows of the sorted worlds back in the
    order of `worlds` (None where they are sorted already: the usual case, no copy)."""
    if worlds.size < 2 or bool((worlds[1:] > worlds[:-1]).all()):
        return worlds, None
    by_world = np.argsort(worlds, kind="stable")
    order = np.empty_like(by_world)
    order[by_world] = np.arange(worlds.size)
    return worlds[by_world], order
