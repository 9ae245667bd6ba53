"""Camera, lidar and noise configuration: mujoco_ros2_control's plugin YAML, read unchanged,
and batchsim's own `sensors:` block, in one file or two.

mujoco_ros2_control's plugin parameters (under any node's `ros__parameters.mujoco_plugins`):

    mujoco_camera_plugin:                          # type mujoco_ros2_control_plugins/CameraPlugin
      camera_publish_rate: 5.0
      <camera>: {policy, frame_name, image_topic, depth_topic, info_topic, trigger_service_name}
    rangefinder_lidar_plugin:                      # type .../RangefinderLidarPlugin
      lidar_publish_rate: 10.0
      <lidar>: {frame_name, min_angle, max_angle, angle_increment, range_min, range_max, laserscan_topic}
    mujoco_3d_lidar_plugin:                        # type .../Mujoco3dLidarPlugin
      <sensor>: {frame_name, topic}

as upstream's plugins read them (mujoco_ros2_control_plugins/src/*.cpp); older spellings are
read too (`camera_type` for `policy`, `publish_rate` and `topic` for the lidar's). The base
velocity plugin's params (`body`, `cmd_vel_topic`, ...) become `base_velocity`, the external
wrench plugin's (`force_arrow_scale`, `torque_arrow_scale`) `external_wrench`: the system runs
both, and batchsim.plugins.config parses them.
Plugins batchsim does not run (the heartbeat and free-joint state plugins, or any other type)
are named in `warnings`, which `batchsim` and `batchsim info` print, with what to use instead.
The same camera and lidar params given as `<param>`s of a
ros2_control `<sensor>` of the camera's (or the lidar's) name are read too, as upstream's
legacy path does; the YAML wins where both set a key (`with_defaults`).

batchsim's block (top level):

    sensors:
      seed: 0                      # noise seed; world i's noise depends on (seed, i) only
      camera_rate: 30              # Hz (default: the plugin's camera_publish_rate, else 5)
      lidar_rate: 10               # Hz
      camera_resolution: [64, 64]  # width, height for every camera (default: the MJCF's)
      cameras: {<camera>: {width, height, frame_name, image_topic, depth_topic, info_topic}}
      lidars:                      # dense lidars cast in bulk, no MJCF sensors needed
        <name>: {site, horizontal: {samples, min_angle, max_angle},
                 vertical: {samples, min_angle, max_angle}, range_min, range_max, frame_name, topic, rate}
      noise:                       # keys: state interfaces, MJCF sensors, cameras, lidars; * and ? match
        "*/position": {stddev: 0.001}
        wrist_force: {stddev: 0.5, bias_stddev: 0.2}
        front_camera: {stddev: 0.01, dropout: 0.01}     # depth
        base_scan: {stddev: 0.02, dropout: 0.01}        # ranges

Files are read as rcl reads parameter files (batchsim.model.params): a key given twice (two
`/**:` blocks, say) is merged, and `mujoco_plugins.<plugin>.<key>: value` is the nested form.
Everything unknown is an error naming the file and the key; plugins of other types
(the heartbeat, free-joint state, ...) are listed in `warnings`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from batchsim.model.params import ParamsError, load_yaml, nest_dotted, read_text
from batchsim.plugins import BaseVelocityConfig, ExternalWrenchConfig
from batchsim.plugins.config import NOT_RUN, RUN, parse_plugin
from batchsim.sensors.noise import Noise

CAMERA_PLUGIN = "mujoco_ros2_control_plugins/CameraPlugin"
RANGEFINDER_PLUGIN = "mujoco_ros2_control_plugins/RangefinderLidarPlugin"
LIDAR3D_PLUGIN = "mujoco_ros2_control_plugins/Mujoco3dLidarPlugin"

_CAMERA_KEYS = (
    "policy", "frame_name", "image_topic", "depth_topic", "info_topic", "trigger_service_name",
    "camera_type", "width", "height",
)  # fmt: skip
_RANGEFINDER_KEYS = (
    "frame_name", "min_angle", "max_angle", "angle_increment", "range_min", "range_max", "laserscan_topic", "topic",
)  # fmt: skip
_RENAMED = {"policy": "camera_type", "laserscan_topic": "topic"}  # upstream's key -> the field it fills
_LIDAR3D_KEYS = ("frame_name", "topic")
_DENSE_KEYS = ("site", "horizontal", "vertical", "range_min", "range_max", "frame_name", "topic", "rate")
_AXIS_KEYS = ("samples", "min_angle", "max_angle")
_NUMBER_KEYS = frozenset({"min_angle", "max_angle", "angle_increment", "range_min", "range_max"})
_SIZE_KEYS = frozenset({"width", "height"})
_BLOCK_KEYS = ("seed", "camera_rate", "lidar_rate", "camera_resolution", "cameras", "lidars", "noise")


class SensorConfigError(ValueError):
    """A bad sensor configuration: one line naming the file and the key at fault."""


@dataclasses.dataclass(frozen=True)
class CameraSettings:
    """Per-camera overrides; None keeps batchsim's default."""

    frame_name: str | None = None
    image_topic: str | None = None
    depth_topic: str | None = None
    info_topic: str | None = None
    camera_type: str | None = None
    width: int | None = None
    height: int | None = None


@dataclasses.dataclass(frozen=True)
class LidarSettings:
    """Per-lidar overrides of a rangefinder or plugin lidar; None keeps what the model gives."""

    frame_name: str | None = None
    topic: str | None = None
    min_angle: float | None = None
    max_angle: float | None = None
    angle_increment: float | None = None
    range_min: float | None = None
    range_max: float | None = None


@dataclasses.dataclass(frozen=True)
class AxisSpec:
    """One axis of a dense lidar: `samples` angles from min_angle to max_angle inclusive."""

    samples: int = 1
    min_angle: float = 0.0
    max_angle: float = 0.0


@dataclasses.dataclass(frozen=True)
class DenseLidarSpec:
    """A lidar of batchsim's own `lidars:` block, cast in bulk from a site."""

    name: str
    site: str
    horizontal: AxisSpec
    vertical: AxisSpec = AxisSpec()
    range_min: float = 0.0
    range_max: float = 100.0
    frame_name: str | None = None
    topic: str | None = None
    rate: float | None = None


@dataclasses.dataclass
class SensorConfig:
    """Everything configurable about cameras, lidars and noise. Empty: batchsim's defaults, no noise.

    Attributes:
      source: the file(s) it came from, for messages.
      seed: the noise seed.
      camera_rate, lidar_rate: Hz, or None for the defaults (5 and 10 Hz, as mujoco_ros2_control).
      camera_resolution: (width, height) for every camera, or None for each MJCF camera's own.
      cameras: per-camera overrides, by MJCF camera name.
      rangefinder_lidars: per-lidar overrides of MJCF rangefinder groups, by group name.
      plugin_lidars: per-sensor overrides of mujoco.plugin.lidar sensors, by sensor name.
      dense_lidars: lidars cast in bulk from sites, batchsim's own.
      noise: noise by name pattern (state interfaces, MJCF sensors, cameras, lidars).
      base_velocity: the BaseVelocityPlugin's params, or None (batchsim.plugins).
      external_wrench: the ExternalWrenchPlugin's params, or None (batchsim.plugins).
      warnings: what was read and ignored (plugins of other types).
    """

    source: str = "<defaults>"
    seed: int = 0
    camera_rate: float | None = None
    lidar_rate: float | None = None
    camera_resolution: tuple[int, int] | None = None
    cameras: dict[str, CameraSettings] = dataclasses.field(default_factory=dict)
    rangefinder_lidars: dict[str, LidarSettings] = dataclasses.field(default_factory=dict)
    plugin_lidars: dict[str, LidarSettings] = dataclasses.field(default_factory=dict)
    dense_lidars: list[DenseLidarSpec] = dataclasses.field(default_factory=list)
    noise: dict[str, Noise] = dataclasses.field(default_factory=dict)
    base_velocity: BaseVelocityConfig | None = None
    external_wrench: ExternalWrenchConfig | None = None
    warnings: list[str] = dataclasses.field(default_factory=list)

    @classmethod
    def load(cls, *sources: str | Path | Mapping[str, Any]) -> SensorConfig:
        """Read YAML files (or already-parsed mappings) into one configuration; later ones win."""
        config = cls()
        names = []
        for source in sources:
            if isinstance(source, Mapping):
                where, document = "<sensor config>", source
            else:
                where = str(source)
                try:
                    document = load_yaml(read_text(Path(source), where), where)
                except ParamsError as e:
                    raise SensorConfigError(str(e)) from None
            names.append(where)
            config._read(document if document is not None else {}, where)
        if names:
            config.source = ", ".join(names)
        return config

    @classmethod
    def from_flags(
        cls,
        files: list[str] | None = None,
        *,
        camera_rate: float | None = None,
        lidar_rate: float | None = None,
        camera_resolution: str | None = None,
        seed: int | None = None,
    ) -> SensorConfig | None:
        """The configuration the command line asks for (`--sensors`, `--camera-rate`, ...), or None
        when it asks for nothing; flags override the files."""
        if not files and camera_rate is None and lidar_rate is None and camera_resolution is None and seed is None:
            return None
        config = cls.load(*(files or []))
        if camera_rate is not None:
            config.camera_rate = _rate(camera_rate, "--camera-rate")
        if lidar_rate is not None:
            config.lidar_rate = _rate(lidar_rate, "--lidar-rate")
        if camera_resolution is not None:
            config.camera_resolution = resolution(camera_resolution, "--camera-resolution")
        if seed is not None:
            if seed < 0:
                raise SensorConfigError(f"--noise-seed: must be >= 0, got {seed}")
            config.seed = seed
        return config

    def with_defaults(
        self,
        cameras: Mapping[str, Mapping[str, str]],
        lidars: Mapping[str, Mapping[str, str]],
        rates: Mapping[str, str],
        where: str,
    ) -> SensorConfig:
        """This configuration over a ros2_control file's camera and lidar settings (the params
        of a `<sensor>` named after a camera or a rangefinder lidar, and the hardware params
        camera_publish_rate, lidar_publish_rate), as mujoco_ros2_control's legacy path reads
        them: a key this configuration sets wins. Params no camera or lidar takes are warned of."""
        out = dataclasses.replace(
            self,
            cameras=dict(self.cameras),
            rangefinder_lidars=dict(self.rangefinder_lidars),
            warnings=list(self.warnings),
        )
        if out.camera_rate is None and "camera_publish_rate" in rates:
            out.camera_rate = _rate(rates["camera_publish_rate"], f"{where}: hardware param camera_publish_rate")
        if out.lidar_rate is None and "lidar_publish_rate" in rates:
            out.lidar_rate = _rate(rates["lidar_publish_rate"], f"{where}: hardware param lidar_publish_rate")
        for table, keys, cls, given in (
            (cameras, _CAMERA_KEYS, CameraSettings, out.cameras),
            (lidars, _RANGEFINDER_KEYS, LidarSettings, out.rangefinder_lidars),
        ):
            for name, params in table.items():
                at = f"{where}: ros2_control sensor {name!r}"
                for key in sorted(set(params) - set(keys)):
                    out.warnings.append(f"{at}: param {key!r} is not a {cls.__name__[:-8].lower()} setting: ignored")
                legacy = _settings(cls, keys, {k: v for k, v in params.items() if k in keys}, at)
                mine = given.get(name)
                if mine is not None:
                    legacy = dataclasses.replace(
                        legacy, **{f.name: v for f in dataclasses.fields(mine) if (v := getattr(mine, f.name)) is not None}
                    )
                given[name] = legacy
        return out

    # --- parsing ---
    def _read(self, document: Any, where: str) -> None:
        if not isinstance(document, Mapping):
            raise SensorConfigError(f"{where}: expected a YAML mapping at the top level")
        found = False
        for key, value in document.items():
            if key == "sensors":
                self._read_block(value, f"{where}: sensors")
                found = True
            elif isinstance(value, Mapping) and isinstance(value.get("ros__parameters"), Mapping):
                plugins = nest_dotted(value["ros__parameters"]).get("mujoco_plugins")
                if plugins is not None:
                    self._read_plugins(plugins, f"{where}: {key}.ros__parameters.mujoco_plugins")
                    found = True
                else:
                    self.warnings.append(f"{where}: {key}: no mujoco_plugins, ignored")
            else:
                raise SensorConfigError(
                    f"{where}: unknown top-level key {key!r} (expected `sensors:` or a node's "
                    "`ros__parameters: mujoco_plugins:` from mujoco_ros2_control)"
                )
        if not found and document:
            raise SensorConfigError(f"{where}: no `sensors:` block and no mujoco_plugins")

    def _read_plugins(self, plugins: Any, where: str) -> None:
        if not isinstance(plugins, Mapping):
            raise SensorConfigError(f"{where}: expected a mapping of plugins")
        for name, params in plugins.items():
            at = f"{where}.{name}"
            if not isinstance(params, Mapping) or "type" not in params:
                raise SensorConfigError(f"{at}: a plugin needs a `type`")
            kind = params["type"]
            rest = {k: v for k, v in params.items() if k != "type"}
            if kind == CAMERA_PLUGIN:
                for key, value in rest.items():
                    if key == "camera_publish_rate":
                        self.camera_rate = _rate(value, f"{at}.{key}")
                    else:
                        self.cameras[str(key)] = _settings(CameraSettings, _CAMERA_KEYS, value, f"{at}.{key}")
            elif kind == RANGEFINDER_PLUGIN:
                for key, value in rest.items():
                    if key in ("lidar_publish_rate", "publish_rate"):
                        self.lidar_rate = _rate(value, f"{at}.{key}")
                    else:
                        self.rangefinder_lidars[str(key)] = _settings(LidarSettings, _RANGEFINDER_KEYS, value, f"{at}.{key}")
            elif kind == LIDAR3D_PLUGIN:
                for key, value in rest.items():
                    self.plugin_lidars[str(key)] = _settings(LidarSettings, _LIDAR3D_KEYS, value, f"{at}.{key}")
            elif kind in RUN:
                self._read_once(kind, str(name), rest, at)
            elif kind in NOT_RUN:
                self.warnings.append(f"{at}: {kind} is not run by batchsim: {NOT_RUN[kind]}")
            else:
                self.warnings.append(f"{at}: plugin type {kind!r} is unknown to batchsim: not run")

    def _read_once(self, kind: str, name: str, params: Mapping[str, Any], at: str) -> None:
        """A plugin of type `kind` the system runs one instance of (batchsim.plugins.config): its
        params into its field."""
        given = getattr(self, RUN[kind][0])
        if given is not None and given.name != name:  # the same instance in a later file replaces it
            raise SensorConfigError(f"{at}: a second {kind.rpartition('/')[2]} ({given.where} is one): batchsim runs one")
        try:
            field, config = parse_plugin(kind, name, params, at)
        except ValueError as e:
            raise SensorConfigError(str(e)) from None
        setattr(self, field, config)

    def _read_block(self, block: Any, where: str) -> None:
        if not isinstance(block, Mapping):
            raise SensorConfigError(f"{where}: expected a mapping")
        unknown = sorted(set(block) - set(_BLOCK_KEYS))
        if unknown:
            raise SensorConfigError(f"{where}: unknown key {unknown[0]!r} (known: {', '.join(_BLOCK_KEYS)})")
        if "seed" in block:
            seed = block["seed"]
            if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
                raise SensorConfigError(f"{where}.seed: must be a non-negative integer, got {seed!r}")
            self.seed = seed
        if "camera_rate" in block:
            self.camera_rate = _rate(block["camera_rate"], f"{where}.camera_rate")
        if "lidar_rate" in block:
            self.lidar_rate = _rate(block["lidar_rate"], f"{where}.lidar_rate")
        if "camera_resolution" in block:
            self.camera_resolution = resolution(block["camera_resolution"], f"{where}.camera_resolution")
        for name, value in _mapping(block.get("cameras", {}), f"{where}.cameras").items():
            self.cameras[str(name)] = _settings(CameraSettings, _CAMERA_KEYS, value, f"{where}.cameras.{name}")
        for name, value in _mapping(block.get("lidars", {}), f"{where}.lidars").items():
            self.dense_lidars.append(_dense(str(name), value, f"{where}.lidars.{name}"))
        for pattern, value in _mapping(block.get("noise", {}), f"{where}.noise").items():
            try:
                self.noise[str(pattern)] = Noise.parse(value, f"{where}.noise.{pattern}")
            except ValueError as e:
                raise SensorConfigError(str(e)) from None


def resolution(value: Any, where: str) -> tuple[int, int]:
    """(width, height) from [w, h] or "WxH"."""
    if isinstance(value, str):
        parts = value.lower().replace("x", " ").split()
    elif isinstance(value, list | tuple):
        parts = list(value)
    else:
        parts = []
    try:
        w, h = (int(p) for p in parts)
    except (TypeError, ValueError):
        raise SensorConfigError(f"{where}: expected width and height (WxH or [w, h]), got {value!r}") from None
    if w < 1 or h < 1 or w > 8192 or h > 8192:
        raise SensorConfigError(f"{where}: width and height must be in 1..8192, got {w}x{h}")
    return w, h


def _mapping(value: Any, where: str) -> Mapping[str, Any]:
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise SensorConfigError(f"{where}: expected a mapping")
    return value


def _rate(value: Any, where: str) -> float:
    try:
        rate = float(value)
    except (TypeError, ValueError):
        raise SensorConfigError(f"{where}: must be a number of Hz, got {value!r}") from None
    if not math.isfinite(rate) or rate <= 0:
        raise SensorConfigError(f"{where}: must be > 0 Hz, got {value!r}")
    return rate


def _settings(cls: type, keys: tuple[str, ...], value: Any, where: str) -> Any:
    value = _mapping(value, where)
    unknown = sorted(set(value) - set(keys))
    if unknown:
        raise SensorConfigError(f"{where}: unknown key {unknown[0]!r} (known: {', '.join(keys)})")
    fields = {f.name for f in dataclasses.fields(cls)}
    out: dict[str, Any] = {}
    for key, raw in value.items():
        if key in _RENAMED and _RENAMED[key] in value:
            raise SensorConfigError(f"{where}: both {key!r} and its older spelling {_RENAMED[key]!r}: give one")
        key = _RENAMED.get(key, key)
        if key not in fields:  # read for compatibility, not used (trigger_service_name)
            continue
        if key in _NUMBER_KEYS:
            out[key] = _number(raw, f"{where}.{key}")  # mujoco_ros2_control gives some as strings ("0.025")
        elif key in _SIZE_KEYS:
            if not isinstance(raw, int) or isinstance(raw, bool) or not 1 <= raw <= 8192:
                raise SensorConfigError(f"{where}.{key}: must be an integer in 1..8192, got {raw!r}")
            out[key] = raw
        else:
            out[key] = str(raw)
    if cls is CameraSettings and out.get("camera_type") not in (None, "streaming", "polled", "disabled"):
        raise SensorConfigError(f"{where}.policy: streaming, polled or disabled, got {out['camera_type']!r}")
    return cls(**out)


def _axis(value: Any, where: str) -> AxisSpec:
    value = _mapping(value, where)
    unknown = sorted(set(value) - set(_AXIS_KEYS))
    if unknown:
        raise SensorConfigError(f"{where}: unknown key {unknown[0]!r} (known: {', '.join(_AXIS_KEYS)})")
    samples = value.get("samples", 1)
    if not isinstance(samples, int) or isinstance(samples, bool) or not 1 <= samples <= 1_000_000:
        raise SensorConfigError(f"{where}.samples: must be a positive integer, got {samples!r}")
    lo, hi = (_number(value.get(k, 0.0), f"{where}.{k}") for k in ("min_angle", "max_angle"))
    if samples > 1 and hi <= lo:
        raise SensorConfigError(f"{where}: max_angle must exceed min_angle for several samples, got {lo:g}, {hi:g}")
    return AxisSpec(samples, lo, hi)


def _number(value: Any, where: str) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise SensorConfigError(f"{where}: must be a number, got {value!r}") from None
    if not math.isfinite(number):
        raise SensorConfigError(f"{where}: must be finite, got {value!r}")
    return number


def _dense(name: str, value: Any, where: str) -> DenseLidarSpec:
    value = _mapping(value, where)
    unknown = sorted(set(value) - set(_DENSE_KEYS))
    if unknown:
        raise SensorConfigError(f"{where}: unknown key {unknown[0]!r} (known: {', '.join(_DENSE_KEYS)})")
    if not isinstance(value.get("site"), str):
        raise SensorConfigError(f"{where}: needs `site`, the MJCF site the rays start from")
    if "horizontal" not in value:
        raise SensorConfigError(f"{where}: needs `horizontal: {{samples, min_angle, max_angle}}`")
    range_min = _number(value.get("range_min", 0.0), f"{where}.range_min")
    range_max = _number(value.get("range_max", 100.0), f"{where}.range_max")
    if not 0 <= range_min < range_max:
        raise SensorConfigError(f"{where}: need 0 <= range_min < range_max, got {range_min:g}, {range_max:g}")
    return DenseLidarSpec(
        name=name,
        site=value["site"],
        horizontal=_axis(value["horizontal"], f"{where}.horizontal"),
        vertical=_axis(value.get("vertical", {}), f"{where}.vertical"),
        range_min=range_min,
        range_max=range_max,
        frame_name=str(value["frame_name"]) if "frame_name" in value else None,
        topic=str(value["topic"]) if "topic" in value else None,
        rate=_rate(value["rate"], f"{where}.rate") if "rate" in value else None,
    )
