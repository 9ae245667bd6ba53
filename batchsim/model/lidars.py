"""Lidars declared in XML that MuJoCo itself does not compile, read and removed before it does.

- `<lidar ref_site= sensor_name= min_angle= max_angle= angle_increment= [range_min=
  range_max=]/>`: mujoco_ros2_control's element (in its converter's `<processed_inputs>`,
  beside a ros2_control block). Its converter replicates one rangefinder per angle; batchsim
  casts the same rays, from the same site and at the same angles, in bulk instead.
- `<extension><plugin plugin="mujoco.plugin.lidar">` instances and the `<sensor><plugin
  instance=.../>` elements that use them: mujoco_ros2_control's 2D/3D lidar (a MuJoCo
  plugin library batchsim does not load), config keys `resolution`, `azimuth_range`,
  `elevation_range`, `max_range`, `min_range`, `update_rate`, `async`.

- Rangefinder sensors named `<name>-<index>` on sites (`rangefinder_groups`): the lidars of
  mujoco_ros2_control's RangefinderLidarPlugin, found in the compiled model.

This module only parses; `batchsim.sensors.suite` resolves the sites against the model.
"""

from __future__ import annotations

import dataclasses
import math
import re
import xml.etree.ElementTree as ET

import mujoco

LIDAR_PLUGIN = "mujoco.plugin.lidar"
LIDAR_PLUGIN_KEYS = ("resolution", "azimuth_range", "elevation_range", "max_range", "min_range", "update_rate", "async")
_ELEMENT_KEYS = ("ref_site", "sensor_name", "min_angle", "max_angle", "angle_increment", "range_min", "range_max")


@dataclasses.dataclass(frozen=True)
class LidarElement:
    """A `<lidar>` element: a planar fan in the site's xy plane from min_angle to max_angle."""

    ref_site: str
    sensor_name: str
    min_angle: float
    max_angle: float
    angle_increment: float
    range_min: float = 0.0
    range_max: float = 1000.0
    where: str = ""


@dataclasses.dataclass(frozen=True)
class PluginLidar:
    """A `mujoco.plugin.lidar` sensor: ncol x nrow rays over an azimuth and elevation range."""

    name: str  # the sensor's name (its plugin instance's when unnamed)
    site: str
    ncol: int
    nrow: int
    azimuth_range: tuple[float, float]
    elevation_range: tuple[float, float]
    min_range: float
    max_range: float
    update_rate: float
    where: str = ""


@dataclasses.dataclass(frozen=True)
class SensorDeclarations:
    """What an MJCF (and its ros2_control file) declare beyond MuJoCo's own sensors."""

    lidar_elements: tuple[LidarElement, ...] = ()
    plugin_lidars: tuple[PluginLidar, ...] = ()
    #: the `<param>`s of each ros2_control `<sensor>` without a mujoco_type (a camera's or a
    #: lidar's, by its name: mujoco_ros2_control's legacy camera and lidar settings)
    sensor_params: tuple[tuple[str, tuple[tuple[str, str], ...]], ...] = ()
    #: the hardware params camera_publish_rate and lidar_publish_rate, where given
    rates: tuple[tuple[str, str], ...] = ()
    where: str = ""  # the ros2_control file, for messages

    def __bool__(self) -> bool:
        return bool(self.lidar_elements or self.plugin_lidars or self.sensor_params or self.rates)

    def merged(self, other: SensorDeclarations) -> SensorDeclarations:
        return SensorDeclarations(
            self.lidar_elements + other.lidar_elements,
            self.plugin_lidars + other.plugin_lidars,
            self.sensor_params + other.sensor_params,
            self.rates + other.rates,
            self.where or other.where,
        )


class DeclarationError(ValueError):
    """A malformed lidar declaration; the message is one line naming the file and element."""


def take_declarations(root: ET.Element, where: str) -> SensorDeclarations:
    """Remove the `<lidar>` elements and `mujoco.plugin.lidar` blocks from an MJCF tree; return them."""
    elements = []
    for parent in list(root.iter()):
        for child in list(parent):
            if child.tag == "lidar" and child.get("ref_site") is not None:
                elements.append(_lidar_element(child, where))
                parent.remove(child)
    plugins = _take_plugin_lidars(root, where)
    return SensorDeclarations(tuple(elements), tuple(plugins))


def lidar_elements_of(root: ET.Element, where: str) -> tuple[LidarElement, ...]:
    """The `<lidar>` elements anywhere in a ros2_control file's document (a URDF's mujoco_inputs),
    read after xacro expanded it, so a lidar inside a false `<xacro:if>` is not one."""
    return tuple(_lidar_element(el, where) for el in root.iter("lidar") if el.get("ref_site") is not None)


def _number(el: ET.Element, key: str, where: str, default: float | None = None) -> float:
    raw = el.get(key)
    if raw is None:
        if default is None:
            raise DeclarationError(f"{where}: <{el.tag}> needs the attribute {key}")
        return default
    try:
        value = float(raw)
    except ValueError:
        raise DeclarationError(f"{where}: <{el.tag}> {key} must be a number, got {raw!r}") from None
    if not math.isfinite(value):
        raise DeclarationError(f"{where}: <{el.tag}> {key} must be finite, got {raw!r}")
    return value


def _lidar_element(el: ET.Element, where: str) -> LidarElement:
    unknown = sorted(set(el.attrib) - set(_ELEMENT_KEYS))
    if unknown:
        raise DeclarationError(f"{where}: <lidar> has an unknown attribute {unknown[0]!r} (known: {', '.join(_ELEMENT_KEYS)})")
    name = el.get("sensor_name") or el.get("ref_site", "")
    at = f"{where}: <lidar sensor_name={name!r}>"
    lo, hi = _number(el, "min_angle", where), _number(el, "max_angle", where)
    step = _number(el, "angle_increment", where)
    if step <= 0:
        raise DeclarationError(f"{at}: angle_increment must be > 0, got {step:g}")
    if hi < lo:
        raise DeclarationError(f"{at}: max_angle {hi:g} is below min_angle {lo:g}")
    return LidarElement(
        ref_site=el.get("ref_site", ""),
        sensor_name=name,
        min_angle=lo,
        max_angle=hi,
        angle_increment=step,
        range_min=_number(el, "range_min", where, 0.0),
        range_max=_number(el, "range_max", where, 1000.0),
        where=where,
    )


def _floats(raw: str, key: str, at: str) -> list[float]:
    try:
        return [float(x) for x in raw.split()]
    except ValueError:
        raise DeclarationError(f"{at}: {key} must be numbers, got {raw!r}") from None


def _take_plugin_lidars(root: ET.Element, where: str) -> list[PluginLidar]:
    configs: dict[str, dict[str, str]] = {}
    for extension in root.findall("extension"):
        for plugin in list(extension.findall("plugin")):
            if plugin.get("plugin") != LIDAR_PLUGIN:
                continue
            extension.remove(plugin)
            for instance in plugin.findall("instance"):
                keys = {c.get("key", ""): c.get("value", "") for c in instance.findall("config")}
                unknown = sorted(set(keys) - set(LIDAR_PLUGIN_KEYS))
                if unknown:
                    raise DeclarationError(
                        f"{where}: {LIDAR_PLUGIN} instance {instance.get('name')!r}: unknown config key "
                        f"{unknown[0]!r} (known: {', '.join(LIDAR_PLUGIN_KEYS)})"
                    )
                configs[instance.get("name", "")] = keys
        if not list(extension):
            root.remove(extension)
    if not configs:
        return []
    lidars = []
    for section in root.findall("sensor"):
        for el in list(section.findall("plugin")):
            instance = el.get("instance", "")
            if instance not in configs:
                continue
            section.remove(el)
            lidars.append(_plugin_lidar(el, instance, configs[instance], where))
        if not list(section):
            root.remove(section)
    return lidars


def _plugin_lidar(el: ET.Element, instance: str, keys: dict[str, str], where: str) -> PluginLidar:
    name = el.get("name") or instance
    at = f"{where}: {LIDAR_PLUGIN} sensor {name!r}"
    if el.get("objtype", "site") != "site" or not el.get("objname"):
        raise DeclarationError(f"{at}: a lidar must be attached to a site (objtype=\"site\" objname=...)")
    resolution = _floats(keys.get("resolution", ""), "resolution", at)
    if len(resolution) != 2 or min(resolution) < 1 or any(r != int(r) for r in resolution):
        raise DeclarationError(f"{at}: resolution must be two positive integers, got {keys.get('resolution')!r}")
    azimuth = _floats(keys.get("azimuth_range", ""), "azimuth_range", at)
    if len(azimuth) != 2 or not -math.pi <= azimuth[0] < azimuth[1] <= math.pi:
        raise DeclarationError(f"{at}: azimuth_range must be two angles with -pi <= min < max <= pi, got {azimuth}")
    elevation = _floats(keys.get("elevation_range", ""), "elevation_range", at)
    if len(elevation) == 1 and resolution[1] == 1:
        elevation = elevation * 2
    if len(elevation) != 2 or (resolution[1] > 1 and elevation[0] >= elevation[1]):
        raise DeclarationError(f"{at}: elevation_range must be min and max (min < max for several rows), got {elevation}")
    if "max_range" not in keys:
        raise DeclarationError(f"{at}: max_range must be given")
    max_range = _floats(keys["max_range"], "max_range", at)
    min_range = _floats(keys.get("min_range", "0"), "min_range", at)
    rate = _floats(keys.get("update_rate", "1"), "update_rate", at)
    if len(max_range) != 1 or len(min_range) != 1 or not 0 <= min_range[0] < max_range[0]:
        raise DeclarationError(f"{at}: need 0 <= min_range < max_range, got {min_range}, {max_range}")
    if len(rate) != 1 or rate[0] < 0:
        raise DeclarationError(f"{at}: update_rate must be >= 0, got {keys.get('update_rate')!r}")
    return PluginLidar(
        name=name,
        site=el.get("objname", ""),
        ncol=int(resolution[0]),
        nrow=int(resolution[1]),
        azimuth_range=(azimuth[0], azimuth[1]),
        elevation_range=(elevation[0], elevation[1]),
        min_range=min_range[0],
        max_range=max_range[0],
        update_rate=rate[0],
        where=where,
    )


_GROUP = re.compile(r"^(.*)-(\d+)$")


@dataclasses.dataclass(frozen=True)
class RangefinderGroup:
    """MJCF rangefinders `<name>-<index>`: one lidar of mujoco_ros2_control's arrangement."""

    name: str
    sensors: tuple[int, ...]  # sensor ids, by index
    sites: tuple[int, ...]  # their sites


def rangefinder_groups(m: mujoco.MjModel) -> list[RangefinderGroup]:
    """Rangefinder sensors named `<name>-<index>` on sites, grouped by name and ordered by index.

    This is how mujoco_ros2_control's RangefinderLidarPlugin finds its lidars, and how
    MuJoCo names the rangefinders of a `<replicate>` (`lidar-00`, `lidar-01`, ...).
    """
    found: dict[str, list[tuple[int, int, int]]] = {}
    for s in range(m.nsensor):
        if int(m.sensor_type[s]) != int(mujoco.mjtSensor.mjSENS_RANGEFINDER):
            continue
        if int(m.sensor_objtype[s]) != int(mujoco.mjtObj.mjOBJ_SITE):
            continue
        match = _GROUP.match(m.sensor(s).name or "")
        if match is None:
            continue
        found.setdefault(match.group(1), []).append((int(match.group(2)), s, int(m.sensor_objid[s])))
    groups = []
    for name, members in found.items():
        members.sort()
        groups.append(RangefinderGroup(name, tuple(s for _, s, _ in members), tuple(site for _, _, site in members)))
    return groups
