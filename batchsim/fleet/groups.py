"""Fleets of several models: groups of worlds, each group its own fleet file's world (an
environment and its robots), numbered and namespaced as one fleet.

```yaml
name: depot                         # optional
groups:
  - name: cells                     # a ROS name token, unique; names the group in messages
    worlds: 4                       # how many worlds of this group
    fleet: cell.yaml                # a fleet file (paths: from this file) ...
  - name: floor
    worlds: 16
    environment: warehouse.xml      # ... or a fleet file's keys inline
    robots:
      - name: amr_{k}
        model: rover
        count: 8
        grid: {origin: [0, 0], spacing: [1.5, 1.5], columns: 4}
```

The groups' worlds are numbered one after the other: here cells are worlds 0-3 and the floor
worlds 4-19 (`world_4/amr_1/...`). Each group is one batch (one system) on the backend; one
loop steps them all under one `/clock` (batchsim.loop.SimLoop.join). Every fault is one
`FleetError` naming the file and the key.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from batchsim.fleet.file import ROS_NAME, FleetError, FleetFile, check_keys, read_fleet, read_source
from batchsim.model.params import ParamsError, read_yaml

_TOP_KEYS = ("name", "groups")
_GROUP_KEYS = ("name", "worlds", "fleet", "environment", "robots")


@dataclasses.dataclass(frozen=True)
class Group:
    """One group of a fleet: `worlds` worlds of one fleet file's world.

    Attributes:
      name: its name (a ROS name token), unique in the fleet.
      worlds: how many worlds it has, at least 1.
      first_world: the fleet's number of its first world (the groups before it, counted).
      fleet: what each of its worlds holds.
      key: where it is declared (`groups[1]`), for messages.
    """

    name: str
    worlds: int
    first_world: int
    fleet: FleetFile
    key: str

    @property
    def world_range(self) -> range:
        """The fleet's numbers of its worlds."""
        return range(self.first_world, self.first_world + self.worlds)


@dataclasses.dataclass(frozen=True)
class FleetGroups:
    """A fleet file's groups, in the order their worlds are numbered.

    Attributes:
      name: the fleet's name (`name:`, else the file's stem, else "fleet").
      path: the file, or None for a mapping.
      groups: the groups.
    """

    name: str
    path: Path | None
    groups: tuple[Group, ...]

    @property
    def nworld(self) -> int:
        """Every group's worlds, added up."""
        return sum(g.worlds for g in self.groups)

    @property
    def where(self) -> str:
        return str(self.path) if self.path is not None else "<fleet>"


def has_groups(source: Any) -> bool:
    """Whether a fleet file or mapping (batchsim.fleet.is_fleet_file) declares `groups:`."""
    if isinstance(source, FleetGroups):
        return True
    if isinstance(source, Mapping):
        return "groups" in source
    if isinstance(source, str | Path) and Path(str(source)).suffix.lower() in (".yaml", ".yml"):
        try:
            data = read_yaml(Path(source).expanduser())
        except ParamsError:
            return False  # read_fleet says what is wrong with it
        return isinstance(data, Mapping) and "groups" in data
    return False


def read_groups(source: str | Path | Mapping[str, Any]) -> FleetGroups:
    """A fleet file with `groups:` (or its mapping), checked: every key known, every group named
    once with a whole number of worlds (at least 1) and one world: a `fleet:` file, or
    `environment:` and `robots:` inline (read as a fleet file's are, paths from this file).

    Raises:
      FleetError: a missing or malformed file, an unknown key, a group without a name, a name
        that is no ROS name or is given twice, a count of worlds below 1, a group with both or
        neither of `fleet` and `robots`, or anything its fleet file gets wrong (batchsim.fleet).
    """
    path, data, base = read_source(source)
    where = str(path) if path is not None else "<fleet>"
    if not isinstance(data, Mapping):
        raise FleetError(f"{where}: a fleet file is a mapping, got {type(data).__name__}")
    check_keys(data, _TOP_KEYS, where, "")
    items = data.get("groups")
    if not isinstance(items, list) or not items:
        raise FleetError(f"{where}: groups: a list of at least one group (name, worlds, and fleet or robots)")
    groups: list[Group] = []
    seen: dict[str, str] = {}
    first = 0
    for k, item in enumerate(items):
        key = f"groups[{k}]"
        group = _group(item, key, where, base, first)
        if group.name in seen:
            raise FleetError(f"{where}: {key}.name: {group.name!r} is taken by {seen[group.name]}: each group needs its own")
        seen[group.name] = key
        groups.append(group)
        first += group.worlds
    name = data.get("name") or (path.stem if path is not None else "fleet")
    if not isinstance(name, str):
        raise FleetError(f"{where}: name: a string, got {name!r}")
    return FleetGroups(name=name, path=path, groups=tuple(groups))


def _group(item: Any, key: str, where: str, base: Path, first: int) -> Group:
    if not isinstance(item, Mapping):
        raise FleetError(f"{where}: {key}: a mapping with name, worlds, and fleet or robots, got {item!r}")
    check_keys(item, _GROUP_KEYS, where, key)
    name = item.get("name")
    if not isinstance(name, str) or not ROS_NAME.match(name):
        raise FleetError(
            f"{where}: {key}.name: {name!r} is not a valid ROS name: use letters, digits and '_', not starting with a digit"
        )
    worlds = item.get("worlds")
    if not isinstance(worlds, int) or isinstance(worlds, bool) or worlds < 1:
        raise FleetError(f"{where}: {key}.worlds: a whole number of worlds, at least 1, got {worlds!r}")
    if ("fleet" in item) == ("robots" in item):
        raise FleetError(f"{where}: {key}: give one of fleet (a fleet file) and robots (with its environment), not both or neither")
    if "fleet" in item:
        if "environment" in item:
            raise FleetError(f"{where}: {key}.environment: the fleet file names its environment: give it there")
        file = item["fleet"]
        if not isinstance(file, str | Path) or not str(file):
            raise FleetError(f"{where}: {key}.fleet: a fleet file, got {file!r}")
        path = Path(str(file)).expanduser()
        try:
            fleet = read_fleet(path if path.is_absolute() else base / path)
        except FleetError as e:  # its own file's line, led by where this one names it
            raise FleetError(f"{where}: {key}.fleet: {e}") from None
    else:
        inline = {"name": name, "robots": item["robots"]}
        if "environment" in item:
            inline["environment"] = item["environment"]
        try:
            fleet = read_fleet(inline, base=base)
        except FleetError as e:  # the inline keys are this file's: say where they sit
            raise FleetError(str(e).replace("<fleet>:", f"{where}: {key}:", 1)) from None
    return Group(name=name, worlds=worlds, first_world=first, fleet=fleet, key=key)
