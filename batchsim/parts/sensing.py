"""The contract's cameras, lidars and sensor noise (batchsim.sensors), a part of the system: the
sensor suite and its configuration, render, render_async and scan over a source of images and
rays (the engine, or a fleet's shards), and the noise on read()'s values with the truth kept
beside it (`true_state`, `true_sensordata`).

The system checks its lifecycle and the world lists; this part gets worlds as (n,) int64 indices.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from concurrent.futures import Future
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from batchsim.model import RobotSpec
from batchsim.parts.readings import Readings
from batchsim.sensors import Camera, Lidar, LidarKind, SensorConfig, SensorSuite
from batchsim.types import Frames, PendingFrames, SensorData


class SensorSource(Protocol):
    """Where images and rays come from: the engine's camera and lidar calls (batchsim.engine), with
    `worlds` ascending and unique."""

    def render_frames(self, camera: Camera, worlds: np.ndarray, copy: bool) -> tuple[np.ndarray, np.ndarray]: ...
    def device_frames(self, camera: Camera) -> tuple[Any, Any]: ...
    def render_frames_later(self, camera: Camera, worlds: np.ndarray) -> Future: ...
    def prepare_rendering(self, cameras: list[Camera]) -> None: ...
    def cast_ranges(self, lidar: Lidar, worlds: np.ndarray, copy: bool) -> np.ndarray: ...
    def device_ranges(self, lidar: Lidar, host: Callable[[], np.ndarray]) -> Any: ...


class Sensing:
    """Cameras, lidars and sensor noise of `nworld` worlds of `spec`, over `readings` (whose host
    arrays the noise goes onto) and `source`; `frozen()` gives the worlds that keep their held,
    noise-free readings."""

    def __init__(
        self,
        spec: RobotSpec,
        nworld: int,
        readings: Readings,
        source: SensorSource,
        frozen: Callable[[], np.ndarray],
    ):
        self.spec, self.nworld = spec, nworld
        self._readings = readings
        self._source = source
        self._frozen = frozen
        self.config: SensorConfig | None = None
        self._suite: SensorSuite | None = None

    @property
    def suite(self) -> SensorSuite:
        """The cameras, lidars and sensor noise of every world, and which worlds want each."""
        if self._suite is None:
            self._suite = SensorSuite.build(self.spec, self.nworld, self.config)
        return self._suite

    def configure(self, config: SensorConfig | str | Path | Mapping[str, Any]) -> SensorConfig:
        """Take a SensorConfig, YAML file or mapping (batchsim.sensors.config); the config, parsed.
        Raises SensorConfigError naming the file and key at fault."""
        if not isinstance(config, SensorConfig):
            config = SensorConfig.load(config)
        self._suite = SensorSuite.build(self.spec, self.nworld, config)
        self.config = config
        return config

    # --- the truth beside the noise ---
    def truth(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The last read()'s readings and sensordata without noise, or None where there is no noise."""
        noise = self.suite.reading_noise
        return None if noise is None else noise.truth

    def noise_free(self) -> tuple[np.ndarray, np.ndarray]:
        """The last read()'s readings `(nworld, ncolumn)` and sensordata `(nworld, nsensordata)`
        without sensor noise: the truth buffers, or the host arrays where there is no noise."""
        truth = self.truth()
        return (self._readings.array, self._readings.sensor_array) if truth is None else truth

    @property
    def true_state(self) -> np.ndarray:
        """(nworld, nstate) float64: `state` without sensor noise; `state` itself when there is none."""
        truth = self.truth()
        return self._readings.state if truth is None else truth[0][:, : len(self.spec.state)]

    @property
    def true_sensordata(self) -> SensorData:
        """Every MJCF sensor by name without noise, (nworld, dim); `sensordata` when there is none."""
        truth = self.truth()
        return self._readings.sensordata if truth is None else SensorData(truth[1], self.spec.sensors)

    def add_noise(self) -> None:
        """Sensor noise on the refreshed host readings (after every read and reset), the truth
        kept; a frozen world keeps its noise-free held readings rather than fresh noise."""
        noise = self.suite.reading_noise
        if noise is None:
            return
        r = self._readings
        self.suite.add_reading_noise(r.array, r.sensor_array)
        frozen = self._frozen()
        if frozen.any():
            truth_readings, truth_sensordata = noise.truth
            r.array[frozen] = truth_readings[frozen]
            r.sensor_array[frozen] = truth_sensordata[frozen]

    # --- cameras ---
    def render(self, camera: str, sel: np.ndarray, copy: bool) -> Frames:
        """`camera` in worlds `sel` (in the caller's order) at the current state, noise added."""
        cam = self.suite.camera(camera)
        ascending, order = _ascending(sel)
        rgb, depth = self._source.render_frames(cam, ascending, copy)
        if order is not None:
            rgb, depth = rgb[order], depth[order]
        self.suite.add_noise(cam.name, depth, sel)  # after the reordering: world w's noise on world w's row
        return Frames(rgb, depth)

    def render_device(self, camera: str) -> Frames:
        """The source's own arrays of every world, no host copy, no noise."""
        return Frames(*self._source.device_frames(self.suite.camera(camera)))

    def render_async(self, camera: str, sel: np.ndarray) -> PendingFrames:
        """A render of `camera` in worlds `sel`, under way (the source's render_frames_later)."""
        cam = self.suite.camera(camera)
        ascending, order = _ascending(sel)
        return PendingFrames(self._source.render_frames_later(cam, ascending), cam.name, sel, self.suite, order)

    def prepare_rendering(self) -> None:
        """What the first render_async would set up inside the loop, now."""
        if self.suite.cameras:
            self._source.prepare_rendering(list(self.suite.cameras.values()))

    # --- lidars ---
    def scan(self, lidar: str, sel: np.ndarray, copy: bool) -> np.ndarray:
        """(n, nray) float32 REP 117 ranges of `lidar` in worlds `sel` (the caller's order), noise added."""
        ld = self.suite.lidar(lidar)
        ascending, order = _ascending(sel)
        ranges = self.ranges(ld, ascending, copy)
        if order is not None:
            ranges = ranges[order]
        self.suite.add_noise(ld.name, ranges, sel)  # after the reordering: world w's noise on world w's row
        return ranges

    def scan_device(self, lidar: str) -> Any:
        """The source's own (nworld, nray) ranges of every world, no noise."""
        ld = self.suite.lidar(lidar)
        return self._source.device_ranges(ld, lambda: self.ranges(ld, np.arange(self.nworld)))

    def ranges(self, ld: Lidar, worlds: np.ndarray, copy: bool = True) -> np.ndarray:
        """Noise-free REP 117 ranges (n, nray) float32 of `ld` in `worlds` (a buffer if not `copy`):
        a rangefinder lidar's from sensordata (as of the last step), the others cast now."""
        if ld.kind is LidarKind.RANGEFINDER:
            sensordata = self.noise_free()[1]
            return ld.ranges(sensordata[np.ix_(worlds, ld.sensor_adr)])
        return self._source.cast_ranges(ld, worlds, copy)


def _ascending(worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """`worlds` (unique) sorted, and the index that puts rows of the sorted worlds back in the
    order of `worlds` (None where they are sorted already: the usual case, no copy)."""
    if worlds.size < 2 or bool((worlds[1:] > worlds[:-1]).all()):
        return worlds, None
    by_world = np.argsort(worlds, kind="stable")
    order = np.empty_like(by_world)
    order[by_world] = np.arange(worlds.size)
    return worlds[by_world], order
