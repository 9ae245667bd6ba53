"""A system's cameras, lidars and noise, resolved against its model, and who wants which.

`SensorSuite.build(spec, nworld, config)` turns the MJCF's cameras and rangefinder groups,
the lidars declared in XML (`batchsim.model.lidars`) and the YAML configuration
(`batchsim.sensors.config`) into `Camera` and `Lidar` data, and the noise patterns into
per-column noise streams. Every name in the configuration must match something in the
model: a typo is an error naming the file, the key and what the model has.

Demand: a camera or lidar is produced only for the worlds someone wants it in.
`want(name, worlds)` / `unwant(name, worlds)` (the ROS bridge calls them from subscriber
counts) keep one (nworld,) bool mask per sensor; `wanted(name)` is that mask, and
`SensorSampler` renders and scans only those worlds.
"""

from __future__ import annotations

import collections
import dataclasses
import fnmatch
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from batchsim.model.lidars import SensorDeclarations, rangefinder_groups
from batchsim.sensors import lidar as lid
from batchsim.sensors.camera import DEFAULT_RESOLUTION, Camera, CameraMode, intrinsics, resolution_of
from batchsim.sensors.config import LidarSettings, SensorConfig, SensorConfigError
from batchsim.sensors.noise import Noise, NoiseStream
from batchsim.types import StateSource

if TYPE_CHECKING:  # batchsim.model imports this package: no import cycle at run time
    from batchsim.model import RobotSpec

DEFAULT_CAMERA_RATE = 5.0  # Hz, mujoco_ros2_control's camera_publish_rate default
DEFAULT_LIDAR_RATE = 10.0  # Hz


class ReadingNoise:
    """Noise on what read() returns, one stream over every noisy value, and the truth beside it.

    Args:
      stream: the noise of the noisy values, state columns first, then sensordata elements.
      state: state column indices (those not read from sensordata).
      sensordata: sensordata indices; the state columns read from sensordata follow them.
      from_sensordata: (state columns, sensordata indices) of the state interfaces that are
        sensor readings: they get the same noisy values as sensordata.
    """

    def __init__(
        self, stream: NoiseStream, state: np.ndarray, sensordata: np.ndarray, from_sensordata: tuple[np.ndarray, np.ndarray]
    ):
        self.stream = stream
        self.state = state
        self.sensordata = sensordata
        self.from_sensordata = from_sensordata
        self.truth: tuple[np.ndarray, np.ndarray] | None = None  # the last readings and sensordata, noise-free

    def apply(self, readings: np.ndarray, sensordata: np.ndarray, ticks: np.ndarray) -> None:
        """Keep the noise-free `readings` (nworld, ncolumn) and `sensordata` (nworld, nsensordata),
        then add the noise to them in place; ticks (nworld,) are each world's reading counters."""
        if self.truth is None:
            self.truth = (np.empty_like(readings), np.empty_like(sensordata))
        np.copyto(self.truth[0], readings)
        np.copyto(self.truth[1], sensordata)
        offsets = self.stream.offsets(np.arange(len(readings)), ticks)
        k = len(self.state)
        if k:
            readings[:, self.state] += offsets[:, :k]
        if len(self.sensordata):
            sensordata[:, self.sensordata] += offsets[:, k:]
            cols, idx = self.from_sensordata
            readings[:, cols] = sensordata[:, idx]


class SensorSuite:
    """The cameras and lidars of a system, their noise, and which worlds want each.

    Attributes:
      cameras: by name, the MJCF cameras not disabled.
      lidars: by name.
      camera_rate, lidar_rate: Hz at which the sampler produces them.
      seed: the noise seed.
      reading_noise: noise on state and sensordata, or None (the default: none).
      config: what it was built from.
    """

    def __init__(
        self,
        nworld: int,
        cameras: dict[str, Camera],
        lidars: dict[str, lid.Lidar],
        camera_rate: float,
        lidar_rate: float,
        seed: int,
        sensor_noise: dict[str, NoiseStream],
        reading_noise: ReadingNoise | None,
        config: SensorConfig,
    ):
        self.nworld = nworld
        self.cameras = cameras
        self.lidars = lidars
        self.camera_rate = camera_rate
        self.lidar_rate = lidar_rate
        self.seed = seed
        self.reading_noise = reading_noise
        self.config = config
        self._sensor_noise = sensor_noise
        self._wanted = {name: np.zeros(nworld, bool) for name in (*cameras, *lidars)}
        # per sensor and world, how many readings were taken: the noise's counter
        self._ticks = {name: np.zeros(nworld, np.uint64) for name in (*cameras, *lidars, "<readings>")}

    # --- lookup ---
    def camera(self, name: str) -> Camera:
        try:
            return self.cameras[name]
        except KeyError:
            raise KeyError(f"no camera named {name!r}; cameras: {', '.join(self.cameras) or 'none'}") from None

    def lidar(self, name: str) -> lid.Lidar:
        try:
            return self.lidars[name]
        except KeyError:
            raise KeyError(f"no lidar named {name!r}; lidars: {', '.join(self.lidars) or 'none'}") from None

    def next_ticks(self, name: str, worlds: np.ndarray) -> np.ndarray:
        """The reading counters of `worlds` for sensor `name`, then advance them."""
        ticks = self._ticks[name]
        out = ticks[worlds].copy()
        ticks[worlds] += np.uint64(1)
        return out

    def add_noise(self, name: str, values: np.ndarray, worlds: np.ndarray) -> None:
        """Add camera `name`'s depth noise, or lidar `name`'s range noise, to `values` (n, ...) in place."""
        stream = self._sensor_noise.get(name)
        if stream is not None and len(worlds):
            stream.apply(values, worlds, self.next_ticks(name, worlds))

    def add_reading_noise(self, readings: np.ndarray, sensordata: np.ndarray) -> None:
        """Add the noise on state and sensordata (read() calls it), keeping the truth in `reading_noise.truth`."""
        if self.reading_noise is not None:
            self.reading_noise.apply(readings, sensordata, self.next_ticks("<readings>", np.arange(self.nworld)))

    # --- demand ---
    def want(self, name: str, worlds: Sequence[int] | np.ndarray | None = None, wanted: bool = True) -> None:
        """Mark `name` wanted (or not) in the listed worlds (None: all). Cheap; any thread."""
        mask = self._mask(name)
        mask[slice(None) if worlds is None else np.asarray(worlds, np.intp)] = wanted

    def unwant(self, name: str, worlds: Sequence[int] | np.ndarray | None = None) -> None:
        self.want(name, worlds, False)

    def wanted(self, name: str) -> np.ndarray:
        """(nworld,) bool: the worlds someone wants `name` in (a live view; do not write)."""
        return self._mask(name)

    def _mask(self, name: str) -> np.ndarray:
        try:
            return self._wanted[name]
        except KeyError:
            known = ", ".join(self._wanted) or "none"
            raise KeyError(f"no camera or lidar named {name!r}; known: {known}") from None

    # --- construction ---
    @classmethod
    def build(cls, spec: RobotSpec, nworld: int, config: SensorConfig | None = None) -> SensorSuite:
        """Resolve `spec`'s cameras and lidars and `config` against the model.

        Raises:
          SensorConfigError: a name the model lacks, a lidar on a missing site, a bad value.
        """
        config = config or SensorConfig()
        m = spec.mjmodel
        declarations = getattr(spec, "sensor_declarations", None) or SensorDeclarations()
        if declarations.sensor_params or declarations.rates:
            config = _with_ros2_control(config, m, declarations)
        where = config.source
        cameras = _cameras(m, config, where)
        lidars = _lidars(m, declarations, config, where, tuple(r.prefix for r in spec.robots))
        clash = set(cameras) & set(lidars)
        if clash:
            raise SensorConfigError(f"{where}: {sorted(clash)[0]!r} names both a camera and a lidar")
        used: set[str] = set()  # patterns that matched a camera or lidar
        sensor_noise: dict[str, NoiseStream] = {}
        for name, size in [*((c, cam.pixels) for c, cam in cameras.items()), *((n, ld.nray) for n, ld in lidars.items())]:
            match = _match(config.noise, name)
            if match is not None:
                used.add(match[0])
                if match[1].active:
                    sensor_noise[name] = NoiseStream(match[1], config.seed, f"sensor:{name}", size)
        reading = _reading_noise(spec, config, used, where)
        return cls(
            nworld=nworld,
            cameras=cameras,
            lidars=lidars,
            camera_rate=config.camera_rate or DEFAULT_CAMERA_RATE,
            lidar_rate=config.lidar_rate or DEFAULT_LIDAR_RATE,
            seed=config.seed,
            sensor_noise=sensor_noise,
            reading_noise=reading,
            config=config,
        )


def _with_ros2_control(config: SensorConfig, m: mujoco.MjModel, declared: SensorDeclarations) -> SensorConfig:
    """`config` over the ros2_control file's settings for the model's cameras and rangefinder lidars."""
    cameras = {m.camera(c).name for c in range(m.ncam)}
    groups = {g.name for g in rangefinder_groups(m)}
    params = {name: dict(p) for name, p in declared.sensor_params}
    return config.with_defaults(
        {n: p for n, p in params.items() if n in cameras},
        {n: p for n, p in params.items() if n in groups},
        dict(declared.rates),
        declared.where,
    )


def _match(patterns: dict[str, Noise], name: str) -> tuple[str, Noise] | None:
    """The first pattern matching `name` exactly, else by wildcard, and its noise."""
    if name in patterns:
        return name, patterns[name]
    for pattern, nz in patterns.items():
        if fnmatch.fnmatchcase(name, pattern):
            return pattern, nz
    return None


def _cameras(m: mujoco.MjModel, config: SensorConfig, where: str) -> dict[str, Camera]:
    names = {m.camera(c).name: c for c in range(m.ncam) if m.camera(c).name}
    unknown = sorted(set(config.cameras) - set(names))
    if unknown:
        raise SensorConfigError(
            f"{where}: camera {unknown[0]!r} is not in the model (cameras: {', '.join(names) or 'none'})"
        )
    cameras = {}
    for name, cid in names.items():
        s = config.cameras.get(name)
        mode = CameraMode(s.camera_type) if s is not None and s.camera_type else CameraMode.STREAMING
        if mode is CameraMode.DISABLED:
            continue
        width, height = config.camera_resolution or resolution_of(m, cid) or DEFAULT_RESOLUTION
        if s is not None and s.width is not None:
            width = s.width
        if s is not None and s.height is not None:
            height = s.height
        cameras[name] = Camera(
            name=name,
            id=cid,
            width=width,
            height=height,
            info=intrinsics(m, cid, width, height),
            frame_id=(s.frame_name if s is not None and s.frame_name else name),
            image_topic=(s.image_topic if s is not None and s.image_topic else f"{name}/image_raw"),
            depth_topic=(s.depth_topic if s is not None and s.depth_topic else f"{name}/depth/image_raw"),
            info_topic=(s.info_topic if s is not None and s.info_topic else f"{name}/camera_info"),
            mode=mode,
        )
    return cameras


def _site(m: mujoco.MjModel, site: str, what: str) -> int:
    sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, site)
    if sid < 0:
        sites = [m.site(i).name for i in range(m.nsite) if m.site(i).name]
        shown = ", ".join(sites[:12]) + (", ..." if len(sites) > 12 else "")
        raise SensorConfigError(f"{what}: the model has no site {site!r} (sites: {shown or 'none'})")
    return sid


def _lidars(
    m: mujoco.MjModel, decl: SensorDeclarations, config: SensorConfig, where: str, robots: tuple[str, ...] = ()
) -> dict[str, lid.Lidar]:
    lidars: dict[str, lid.Lidar] = {}

    def add(ld: lid.Lidar, what: str) -> None:
        if ld.name in lidars:
            raise SensorConfigError(f"{what}: a second lidar named {ld.name!r}")
        lidars[ld.name] = ld

    # MJCF rangefinders in mujoco_ros2_control's arrangement, read from sensordata
    groups = {g.name: g for g in rangefinder_groups(m)}
    unknown = sorted(set(config.rangefinder_lidars) - set(groups))
    if unknown:
        raise SensorConfigError(
            f"{where}: mujoco_rangefinder_plugin lidar {unknown[0]!r}: the model has no rangefinders "
            f"{unknown[0]}-00, {unknown[0]}-01, ... (groups: {', '.join(groups) or 'none'})"
        )
    for name, group in groups.items():
        s = config.rangefinder_lidars.get(name) or LidarSettings()
        frame, dirs, lo, hi, step = lid.group_geometry(m, group)
        # the plugin YAML's angles label the message, as mujoco_ros2_control publishes them
        lo = s.min_angle if s.min_angle is not None else lo
        hi = s.max_angle if s.max_angle is not None else hi
        step = s.angle_increment if s.angle_increment is not None else step
        rmin = s.range_min if s.range_min is not None else 0.0
        rmax = s.range_max if s.range_max is not None else lid.DEFAULT_RANGE_MAX
        lid.check_range(name, rmin, rmax, where)
        add(
            lid.Lidar(
                name=name,
                kind=lid.LidarKind.RANGEFINDER,
                site=m.site(frame).name,
                site_id=frame,
                body_id=int(m.site_bodyid[group.sites[0]]),
                directions=dirs,
                ncol=len(group.sensors),
                nrow=1,
                angle_min=lo,
                angle_max=hi,
                angle_increment=step,
                elevation_min=0.0,
                elevation_max=0.0,
                range_min=rmin,
                range_max=rmax,
                frame_id=s.frame_name or m.site(frame).name,
                topic=s.topic or "",
                sensor_adr=np.array([m.sensor_adr[s_id] for s_id in group.sensors], np.intp),
            ),
            where,
        )

    # <lidar> elements: the same fan, cast in bulk
    for el in decl.lidar_elements:
        what = f"{el.where}: <lidar sensor_name={el.sensor_name!r}>"
        sid = _site(m, el.ref_site, what)
        angles = lid.element_angles(el.min_angle, el.max_angle, el.angle_increment)
        s = config.rangefinder_lidars.get(el.sensor_name) or LidarSettings()
        rmin = s.range_min if s.range_min is not None else el.range_min
        rmax = s.range_max if s.range_max is not None else el.range_max
        lid.check_range(el.sensor_name, rmin, rmax, what)
        add(
            lid.Lidar(
                name=el.sensor_name,
                kind=lid.LidarKind.RAYCAST,
                site=el.ref_site,
                site_id=sid,
                body_id=int(m.site_bodyid[sid]),  # as the rangefinders it stands for
                directions=lid.fan(angles, [0.0]),
                ncol=len(angles),
                nrow=1,
                angle_min=float(angles[0]),
                angle_max=float(angles[-1]),
                angle_increment=el.angle_increment,
                elevation_min=0.0,
                elevation_max=0.0,
                range_min=rmin,
                range_max=rmax,
                frame_id=s.frame_name or el.ref_site,
                topic=s.topic or "",
            ),
            what,
        )

    # mujoco.plugin.lidar sensors
    unknown = sorted(set(config.plugin_lidars) - {p.name for p in decl.plugin_lidars})
    if unknown:
        known = ", ".join(p.name for p in decl.plugin_lidars) or "none"
        raise SensorConfigError(f"{where}: mujoco_3d_lidar_plugin sensor {unknown[0]!r} is not in the model (lidar plugin sensors: {known})")
    for p in decl.plugin_lidars:
        what = f"{p.where}: mujoco.plugin.lidar sensor {p.name!r}"
        sid = _site(m, p.site, what)
        azimuth = lid.linspace(*p.azimuth_range, p.ncol) if p.ncol > 1 else np.zeros(1)
        elevation = lid.linspace(*p.elevation_range, p.nrow)
        s = config.plugin_lidars.get(p.name) or LidarSettings()
        add(
            lid.Lidar(
                name=p.name,
                kind=lid.LidarKind.RAYCAST,
                site=p.site,
                site_id=sid,
                body_id=-1,  # the plugin's rays see every geom
                directions=lid.fan(azimuth, elevation),
                ncol=p.ncol,
                nrow=p.nrow,
                angle_min=float(azimuth[0]),
                angle_max=float(azimuth[-1]),
                angle_increment=float(azimuth[1] - azimuth[0]) if p.ncol > 1 else 0.0,
                elevation_min=float(elevation[0]),
                elevation_max=float(elevation[-1]),
                range_min=p.min_range,
                range_max=p.max_range,
                frame_id=s.frame_name or p.site,
                topic=s.topic or "",
                rate=p.update_rate or None,
            ),
            what,
        )

    # batchsim's own dense lidars
    for d in config.dense_lidars:
        what = f"{where}: sensors.lidars.{d.name}"
        sid = _site(m, d.site, what)
        azimuth = lid.linspace(d.horizontal.min_angle, d.horizontal.max_angle, d.horizontal.samples)
        elevation = lid.linspace(d.vertical.min_angle, d.vertical.max_angle, d.vertical.samples)
        add(
            lid.Lidar(
                name=d.name,
                kind=lid.LidarKind.RAYCAST,
                site=d.site,
                site_id=sid,
                body_id=int(m.site_bodyid[sid]),
                directions=lid.fan(azimuth, elevation),
                ncol=d.horizontal.samples,
                nrow=d.vertical.samples,
                angle_min=float(azimuth[0]),
                angle_max=float(azimuth[-1]),
                angle_increment=float(azimuth[1] - azimuth[0]) if len(azimuth) > 1 else 0.0,
                elevation_min=float(elevation[0]),
                elevation_max=float(elevation[-1]),
                range_min=d.range_min,
                range_max=d.range_max,
                frame_id=d.frame_name or d.site,
                topic=d.topic or "",
                rate=d.rate,
            ),
            what,
        )
    return _default_topics(lidars, where, robots)


def _default_topics(lidars: dict[str, lid.Lidar], where: str, robots: tuple[str, ...] = ()) -> dict[str, lid.Lidar]:
    """Lidars without a configured topic publish on `scan` (2D) or `points` (3D), as mujoco_ros2_control's,
    or on `<lidar>/scan`, `<lidar>/points` where several would share one; in a world of several
    robots (`robots`: their prefixes, batchsim.fleet) each robot's under its own namespace, as it
    alone would (`amr_1/scan`). A clash left is an error."""
    prefix = {name: next((p for p in robots if name.startswith(p)), "") for name in lidars}
    base = {name: "points" if ld.is_3d else "scan" for name, ld in lidars.items() if not ld.topic}
    count = collections.Counter((prefix[name], b) for name, b in base.items())

    def topic(name: str) -> str:
        p, b = prefix[name], base[name]
        return p + b if count[(p, b)] == 1 else f"{name}/{b}"

    out = {name: ld if ld.topic else dataclasses.replace(ld, topic=topic(name)) for name, ld in lidars.items()}
    seen: dict[str, str] = {}
    for name, ld in out.items():
        if ld.topic in seen:
            raise SensorConfigError(f"{where}: lidars {seen[ld.topic]!r} and {name!r} both publish on {ld.topic!r}")
        seen[ld.topic] = name
    return out


def _reading_noise(spec: RobotSpec, config: SensorConfig, used: set[str], where: str) -> ReadingNoise | None:
    """Match the noise patterns to state interfaces and MJCF sensors; one that matches nothing at
    all (nor a camera or lidar, `used`) is an error. A value matched by several patterns takes
    the first's noise."""
    state: dict[int, Noise] = {}
    elements: dict[int, Noise] = {}
    for pattern, nz in config.noise.items():
        sensors = [s for s in spec.sensors if fnmatch.fnmatchcase(s.name, pattern)]
        columns = [
            i for i, c in enumerate(spec.state) if c.source is not StateSource.SENSORDATA and fnmatch.fnmatchcase(c.name, pattern)
        ]
        # a sensor by name, or one of its state interfaces ("wrist_force/force.x"), names sensordata elements
        matched = {s.adr + k for s in sensors for k in range(s.dim)} | {
            c.index for c in spec.state if c.source is StateSource.SENSORDATA and fnmatch.fnmatchcase(c.name, pattern)
        }
        if not columns and not matched:
            if pattern in used:
                continue
            raise SensorConfigError(
                f"{where}: noise pattern {pattern!r} matches no state interface, sensor, camera or lidar "
                f"({_examples(spec)})"
            )
        if nz.dropout:
            raise SensorConfigError(f"{where}: noise {pattern!r}: dropout is for depth and lidar ranges only")
        for c in columns:
            state.setdefault(c, nz)
        for e in sorted(matched):
            elements.setdefault(e, nz)
    state = {c: nz for c, nz in state.items() if nz.active}
    elements = {e: nz for e, nz in elements.items() if nz.active}
    if not state and not elements:
        return None
    per_value = [*state.values(), *elements.values()]
    readings = [i for i, c in enumerate(spec.state) if c.source is StateSource.SENSORDATA]
    return ReadingNoise(
        NoiseStream(per_value, config.seed, "readings", len(per_value)),
        np.array(list(state), np.intp),
        np.array(list(elements), np.intp),
        (np.array(readings, np.intp), np.array([spec.state[i].index for i in readings], np.intp)),
    )


def _examples(spec: RobotSpec) -> str:
    names: Iterable[str] = [c.name for c in spec.state[:4]] + [s.name for s in spec.sensors[:3]]
    return "e.g. " + ", ".join(names) if names else "the model has none"
