"""The fleet file: what a world holds (an environment and the robots in it), parsed and checked
without compiling anything.

```yaml
environment: warehouse.xml          # optional MJCF: floor, shelves, objects (paths: from this file)
robots:
  - name: amr_1                     # its namespace inside the world: a ROS name token
    model: rover                    # a shipped name, an MJCF (a Menagerie scene or robot file), a URDF
    pose: [0.0, 0.0, 0.0, 0.0]      # x, y, z, yaw (radians) in the world; default the origin
    controllers: amr.yaml           # optional: else the model's default controllers
    sensors: amr_sensors.yaml       # optional: its sensors/plugins YAML, as for the robot alone
    ros2_control: amr.urdf          # optional: the description whose blocks narrow its interfaces
    keyframe: home                  # optional: the robot's own keyframe to start in
  - name: amr_{k}                   # `count` robots, k = 1 .. count, placed by a rule:
    model: rover
    count: 6
    grid: {origin: [0, 0, 0], spacing: [1.5, 1.5], columns: 3, yaw: 0.0}
  - name: cart_{k}                  # or at random, drawn per world from the seed (a floating base only):
    model: rover
    count: 4
    random: {area: [-3, -3, 3, 3], yaw: [-3.14, 3.14], min_distance: 0.8}
```

A Python mapping of the same shape works too (`batchsim.make({...}, nworld)`); relative paths
in it are taken from the working directory. Paths may name environment variables
(`model: ${MENAGERIE}/universal_robots_ur5e/ur5e.xml`). Strings live here only: every fault is one
`FleetError` naming the file and the key.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from batchsim.model.params import ParamsError, read_yaml
from batchsim.model.spec import ModelError

#: a ROS name token: what a robot's (and a group's) name must be
ROS_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_VARIABLE = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)\}|\$([A-Za-z_][A-Za-z0-9_]*)")
_ROBOT_KEYS = ("name", "model", "pose", "controllers", "sensors", "ros2_control", "keyframe", "count", "grid", "random")
_GRID_KEYS = ("origin", "spacing", "columns", "yaw")
_RANDOM_KEYS = ("area", "yaw", "min_distance", "z")
_TOP_KEYS = ("environment", "robots", "name")


class FleetError(ModelError):
    """A fleet file or mapping that cannot be used: one line, naming the file and the key."""


@dataclasses.dataclass(frozen=True)
class RandomPlacement:
    """Robots placed at random in each world, from the randomization's seed and the world's
    number (batchsim.variation's draws): x, y uniform in `area`, yaw uniform in `yaw`, at
    least `min_distance` apart (metres, between base origins), z as `z`.

    Attributes:
      key: where it is declared (`robots[1].random`), for messages.
      area: (xmin, ymin, xmax, ymax) in the world frame.
      yaw: (low, high) radians.
      min_distance: metres between any two robots the rule places.
      z: the height of every robot's pose.
    """

    key: str
    area: tuple[float, float, float, float]
    yaw: tuple[float, float]
    min_distance: float
    z: float = 0.0


@dataclasses.dataclass(frozen=True)
class RobotEntry:
    """One robot of a world, as the fleet file places it.

    Attributes:
      name: its namespace inside the world (a ROS name token), unique in the world.
      model: a shipped model's name or a file (MJCF or URDF/xacro; relative to the fleet file).
      pose: (x, y, z, yaw) in the world frame, yaw in radians about +z.
      controllers: its controller_manager YAML, or None: the model's default controllers.
      sensors: its sensors/plugins YAML (batchsim.sensors), written for the robot alone, or
        None; batchsim.fleet.sensors names it as the world does.
      ros2_control: the description whose `<ros2_control>` blocks narrow its interfaces, or None.
      keyframe: its own keyframe to start in (name or index), or None: `home` where it has one.
      key: where it is declared, for messages: `robots[2]` (`robots[2] (amr_3)` for one of a count).
      grid: the key of the grid rule that placed it (`robots[2].grid`), or None for a pose.
      random: the rule that places it at random in each world, or None.
    """

    name: str
    model: str
    pose: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    controllers: Path | None = None
    sensors: Path | None = None
    ros2_control: str | None = None
    keyframe: str | int | None = None
    key: str = ""
    grid: str | None = None
    random: RandomPlacement | None = None


@dataclasses.dataclass(frozen=True)
class FleetFile:
    """What every world of a fleet holds.

    Attributes:
      name: the world model's name (`name:`, else the file's stem, else "fleet").
      path: the fleet file, or None for a mapping.
      environment: the environment MJCF, or None: an empty world (a floor is the robots' own).
      robots: the robots, in the order their interfaces are exported.
    """

    name: str
    path: Path | None
    environment: Path | None
    robots: tuple[RobotEntry, ...]

    @property
    def where(self) -> str:
        """The file for messages (`<fleet>` for a mapping)."""
        return str(self.path) if self.path is not None else "<fleet>"

    def robot(self, name: str) -> RobotEntry:
        for r in self.robots:
            if r.name == name:
                return r
        raise FleetError(f"{self.where}: no robot named {name!r} (robots: {', '.join(r.name for r in self.robots)})")


def is_fleet_file(model: Any) -> bool:
    """Whether `model` is a fleet: a FleetFile, a mapping with `robots`, or a .yaml/.yml file."""
    if isinstance(model, FleetFile):
        return True
    if isinstance(model, Mapping):
        return "robots" in model
    return isinstance(model, str | Path) and Path(str(model)).suffix.lower() in (".yaml", ".yml")


def read_fleet(source: str | Path | Mapping[str, Any], *, base: Path | None = None) -> FleetFile:
    """A fleet file (YAML) or its mapping, checked: every key known, every robot placed. A
    mapping's relative paths are taken from `base` (default: the working directory; a group
    written inline in a file of groups: that file's folder, batchsim.fleet.groups).

    Raises:
      FleetError: a missing or malformed file, an unknown key, a robot without a name or model,
        a name that is no ROS name or is given twice, a bad pose or grid, a count of 0.
    """
    path, data, base = read_source(source, base)
    where = str(path) if path is not None else "<fleet>"
    if isinstance(data, Mapping) and "groups" in data and "robots" not in data:
        raise FleetError(
            f"{where}: groups: a fleet of several groups of worlds is several systems: batchsim --fleet FILE, "
            "or batchsim.make_groups(FILE) in Python"
        )
    if not isinstance(data, Mapping):
        raise FleetError(f"{where}: a fleet file is a mapping with a `robots:` list, got {type(data).__name__}")
    check_keys(data, _TOP_KEYS, where, "")
    robots = data.get("robots")
    if not isinstance(robots, list) or not robots:
        raise FleetError(f"{where}: robots: a list of at least one robot (name, model, pose)")
    environment = data.get("environment")
    env_path = None
    if environment is not None:
        if not isinstance(environment, str | Path) or not str(environment):
            raise FleetError(f"{where}: environment: an MJCF file, got {environment!r}")
        env_path = _file(base, _expand(str(environment), where, "environment"))
        if not env_path.is_file():
            raise FleetError(f"{where}: environment: no such file {str(env_path)!r}")
    entries: list[RobotEntry] = []
    for k, item in enumerate(robots):
        entries += _robots(item, f"robots[{k}]", where, base)
    seen: dict[str, str] = {}
    for r in entries:
        if r.name in seen:
            raise FleetError(f"{where}: {r.key}: the name {r.name!r} is taken by {seen[r.name]}: each robot needs its own")
        seen[r.name] = r.key
    name = data.get("name") or (path.stem if path is not None else "fleet")
    if not isinstance(name, str):
        raise FleetError(f"{where}: name: a string, got {name!r}")
    return FleetFile(name=name, path=path, environment=env_path, robots=tuple(entries))


def read_source(source: str | Path | Mapping[str, Any], base: Path | None = None) -> tuple[Path | None, Any, Path]:
    """(the file or None, its contents, the folder its relative paths start from) of a fleet file
    or mapping (a mapping's from `base`, else the working directory); FleetError for a file
    missing or malformed, named."""
    if isinstance(source, Mapping):
        return None, source, base if base is not None else Path.cwd()
    path = Path(source).expanduser()
    try:
        data = read_yaml(path)  # the project's one YAML loader: a missing file, a malformed one, named
    except ParamsError as e:
        raise FleetError(str(e)) from None
    return path, data, path.parent


def _robots(item: Any, key: str, where: str, base: Path) -> list[RobotEntry]:
    """The robots one `robots:` item declares: one, or `count` placed on a grid."""
    if not isinstance(item, Mapping):
        raise FleetError(f"{where}: {key}: a mapping with name and model, got {item!r}")
    check_keys(item, _ROBOT_KEYS, where, key)
    for needed in ("name", "model"):
        if needed not in item or item[needed] in (None, ""):
            raise FleetError(f"{where}: {key}: {needed} is missing")
    name, model = item["name"], item["model"]
    if not isinstance(name, str) or not isinstance(model, str | Path):
        raise FleetError(f"{where}: {key}: name and model are strings")
    count = item.get("count", 1)
    if not isinstance(count, int) or isinstance(count, bool) or count < 1:
        raise FleetError(f"{where}: {key}.count: a whole number of robots, at least 1, got {count!r}")
    rules = [k for k in ("pose", "grid", "random") if k in item]
    if len(rules) > 1:
        raise FleetError(f"{where}: {key}: give one of pose, grid and random, not {' and '.join(rules)}")
    if count > 1 and not {"grid", "random"} & set(rules):
        raise FleetError(
            f"{where}: {key}: {count} robots need a placement rule: grid: {{origin, spacing, columns}} "
            "or random: {area, min_distance}"
        )
    if count > 1 and "{k}" not in name:
        raise FleetError(f"{where}: {key}.name: {name!r} names {count} robots: put {{k}} in it (e.g. 'amr_{{k}}')")
    random = _random(item["random"], count, where, f"{key}.random") if "random" in item else None
    if random is not None:  # where they stand in the world's model; each world draws its own
        poses = _spread(random, count)
    elif "grid" in item:
        poses = _grid(item["grid"], count, where, f"{key}.grid")
    else:
        poses = [_pose(item.get("pose", (0.0, 0.0, 0.0, 0.0)), where, f"{key}.pose")]
    files = {
        field: _file(base, _expand(str(item[field]), where, f"{key}.{field}")) if item.get(field) not in (None, "") else None
        for field in ("controllers", "sensors")
    }
    for field, file in files.items():
        if file is not None and str(file).lower() != "none" and not file.is_file():
            raise FleetError(f"{where}: {key}.{field}: no such file {str(file)!r}")
    ros2_control = item.get("ros2_control")
    if ros2_control is not None:
        ros2_control = _file_with_args(base, _expand(str(ros2_control), where, f"{key}.ros2_control"))
    model_text = _expand(str(model), where, f"{key}.model")
    if _looks_like_file(model_text):
        model_text = _file_with_args(base, model_text)
    keyframe = item.get("keyframe")
    if keyframe is not None and not isinstance(keyframe, str | int):
        raise FleetError(f"{where}: {key}.keyframe: a keyframe's name or index, got {keyframe!r}")
    out = []
    for k, pose in enumerate(poses, start=1):
        robot_name = name.replace("{k}", str(k))
        if not ROS_NAME.match(robot_name):
            raise FleetError(
                f"{where}: {key}.name: {robot_name!r} is not a valid ROS name: use letters, digits and '_', "
                "not starting with a digit"
            )
        out.append(
            RobotEntry(
                name=robot_name,
                model=model_text,
                pose=pose,
                controllers=files["controllers"],
                sensors=files["sensors"],
                ros2_control=ros2_control,
                keyframe=keyframe,
                key=key if count == 1 else f"{key} ({robot_name})",
                grid=f"{key}.grid" if "grid" in item else None,
                random=random,
            )
        )
    return out


def check_keys(item: Mapping[str, Any], keys: Sequence[str], where: str, key: str) -> None:
    """FleetError naming `where`, `key` and the first key of `item` not among `keys`."""
    unknown = sorted(str(k) for k in item if k not in keys)
    if unknown:
        at = f"{key}." if key else ""
        raise FleetError(f"{where}: {at}{unknown[0]}: unknown key (known: {', '.join(keys)})")


def _numbers(value: Any, n: Sequence[int], where: str, key: str, what: str) -> list[float]:
    if not isinstance(value, list | tuple) or len(value) not in n:
        raise FleetError(f"{where}: {key}: {what}, got {value!r}")
    try:
        out = [float(v) for v in value]
    except (TypeError, ValueError):
        raise FleetError(f"{where}: {key}: {what}, got {value!r}") from None
    if not all(math.isfinite(v) for v in out):
        raise FleetError(f"{where}: {key}: finite numbers, got {value!r}")
    return out


def _pose(value: Any, where: str, key: str) -> tuple[float, float, float, float]:
    x, y, z, yaw = (_numbers(value, (3, 4), where, key, "[x, y, z, yaw] (yaw in radians, optional)") + [0.0])[:4]
    return (x, y, z, yaw)


def _grid(value: Any, count: int, where: str, key: str) -> list[tuple[float, float, float, float]]:
    """`count` poses, row by row: origin + (column * spacing_x, row * spacing_y)."""
    if not isinstance(value, Mapping):
        raise FleetError(f"{where}: {key}: a mapping with origin, spacing and columns")
    check_keys(value, _GRID_KEYS, where, key)
    origin = (_numbers(value.get("origin", [0.0, 0.0, 0.0]), (2, 3), where, f"{key}.origin", "[x, y] or [x, y, z]")
              + [0.0])[:3]  # fmt: skip
    if "spacing" not in value:
        raise FleetError(f"{where}: {key}.spacing is missing: [dx, dy] between neighbours, in metres")
    dx, dy = _numbers(value["spacing"], (2,), where, f"{key}.spacing", "[dx, dy] in metres")
    columns = value.get("columns", count)
    if not isinstance(columns, int) or isinstance(columns, bool) or columns < 1:
        raise FleetError(f"{where}: {key}.columns: a whole number, at least 1, got {columns!r}")
    yaw = value.get("yaw", 0.0)
    if not isinstance(yaw, int | float) or isinstance(yaw, bool) or not math.isfinite(yaw):
        raise FleetError(f"{where}: {key}.yaw: radians, got {yaw!r}")
    if count > 1 and (abs(dx) < 1e-9 and columns > 1 or abs(dy) < 1e-9 and count > columns):
        raise FleetError(f"{where}: {key}.spacing: {value['spacing']!r} puts several robots on one spot")
    return [
        (origin[0] + (k % columns) * dx, origin[1] + (k // columns) * dy, origin[2], float(yaw))
        for k in range(count)
    ]


def _random(value: Any, count: int, where: str, key: str) -> RandomPlacement:
    if not isinstance(value, Mapping):
        raise FleetError(f"{where}: {key}: a mapping with area and min_distance")
    check_keys(value, _RANDOM_KEYS, where, key)
    if "area" not in value:
        raise FleetError(f"{where}: {key}.area is missing: [xmin, ymin, xmax, ymax] in metres")
    x0, y0, x1, y1 = _numbers(value["area"], (4,), where, f"{key}.area", "[xmin, ymin, xmax, ymax] in metres")
    if not (x1 > x0 and y1 > y0):
        raise FleetError(f"{where}: {key}.area: {value['area']!r} is empty (xmax > xmin and ymax > ymin)")
    lo, hi = _numbers(value.get("yaw", [-math.pi, math.pi]), (2,), where, f"{key}.yaw", "[low, high] in radians")
    if hi < lo:
        raise FleetError(f"{where}: {key}.yaw: {hi:g} is below {lo:g}")
    d = value.get("min_distance", 0.0)
    if not isinstance(d, int | float) or isinstance(d, bool) or not (math.isfinite(d) and d >= 0):
        raise FleetError(f"{where}: {key}.min_distance: metres >= 0, got {d!r}")
    z = value.get("z", 0.0)
    if not isinstance(z, int | float) or isinstance(z, bool) or not math.isfinite(z):
        raise FleetError(f"{where}: {key}.z: metres, got {z!r}")
    # discs of diameter min_distance dropped at random cover at most ~55 % of a plane (random
    # sequential adsorption jams there); the area's border lets half a disc out
    room = (x1 - x0 + d) * (y1 - y0 + d) * 0.5 / (math.pi / 4 * d * d) if d > 0 else math.inf
    if count > room:
        raise FleetError(
            f"{where}: {key}: {count} robots {d:g} m apart do not fit in {x1 - x0:g} x {y1 - y0:g} m "
            "(widen the area or lower min_distance)"
        )
    return RandomPlacement(key, (x0, y0, x1, y1), (lo, hi), float(d), float(z))


def _spread(rule: RandomPlacement, count: int) -> list[tuple[float, float, float, float]]:
    """`count` poses on a grid filling the rule's area: where the world's model puts them."""
    x0, y0, x1, y1 = rule.area
    columns = max(1, math.ceil(math.sqrt(count * (x1 - x0) / (y1 - y0))))
    rows = math.ceil(count / columns)
    return [
        (x0 + (x1 - x0) * (k % columns + 0.5) / columns, y0 + (y1 - y0) * (k // columns + 0.5) / rows, rule.z, 0.0)
        for k in range(count)
    ]


def _looks_like_file(text: str) -> bool:
    first = text.split()[0] if text.split() else text
    return "/" in first or Path(first).suffix.lower() in (".xml", ".mjcf", ".urdf", ".xacro")


def _expand(text: str, where: str, key: str) -> str:
    """`$VAR` and `${VAR}` from the environment (a Menagerie checkout: `${MENAGERIE}/...`);
    FleetError naming an unset one."""
    for name in _VARIABLE.findall(text):
        var = name[0] or name[1]
        if var not in os.environ:
            raise FleetError(f"{where}: {key}: ${{{var}}} is not set (export {var}=... before running)")
    return os.path.expandvars(text)


def _file(base: Path, value: Any) -> Path:
    path = Path(str(value)).expanduser()
    return path if path.is_absolute() or str(value).lower() == "none" else base / path


def _file_with_args(base: Path, text: str) -> str:
    """A file (relative to `base`) that xacro arguments may follow: `arm.urdf.xacro prefix:=a_`."""
    first, _, rest = text.strip().partition(" ")
    path = _file(base, first)
    return f"{path} {rest}".strip()
