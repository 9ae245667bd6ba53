"""Fleet files: several robots in one world, composed with MuJoCo's MjSpec attach.

    file.py      the fleet file (YAML or a mapping): environment, robots, poses, grids; checked
    compose.py   one world's RobotSpec from it: each robot attached under `<robot>/`, its
                 interfaces, sensors and bodies recorded per robot (RobotSpec.robots)
    sensors.py   each robot's own sensors file (cameras, lidars, noise, plugins), checked against
                 the robot alone and named as the world names it; merged into RobotSpec.sensor_config
    reset.py     one robot of a world reset alone, the others left as they are
    view.py      the world's spec as one robot names it (its controllers see only their robot)
    groups.py    a fleet of several groups of worlds (`groups:`), each its own fleet file's world,
                 numbered as one fleet (batchsim.make_groups, `batchsim --fleet`)

`load_fleet(source)` reads, composes and checks a fleet: what `batchsim.make` and the command
line's `--fleet` take.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from batchsim.fleet.compose import compose, overlaps, robot_of_body
from batchsim.fleet.file import FleetError, FleetFile, RobotEntry, is_fleet_file, read_fleet
from batchsim.fleet.view import robot_view
from batchsim.model.spec import RobotSpec

#: worlds whose random placements load_fleet draws to check that every rule finds room
PLACEMENT_CHECK = 64

__all__ = [
    "FleetError",
    "FleetFile",
    "RobotEntry",
    "compose",
    "is_fleet_file",
    "load_fleet",
    "overlaps",
    "read_fleet",
    "robot_of_body",
    "robot_view",
]


def load_fleet(source: str | Path | Mapping[str, Any] | FleetFile) -> RobotSpec:
    """The RobotSpec of a world of the fleet's robots, checked: robots a grid rule places into
    each other are refused (FleetError naming the rule); robots placed by hand that overlap at
    their start are a warning (in `spec.warnings`) naming both and how deep."""
    fleet = source if isinstance(source, FleetFile) else read_fleet(source)
    spec = compose(fleet)
    for a, b, depth, g1, g2 in overlaps(spec):
        ra, rb = fleet.robot(a), fleet.robot(b)
        line = f"robots {a} and {b} overlap at their start pose by {depth * 1000:.0f} mm (geoms {g1!r} and {g2!r})"
        if ra.grid is not None and ra.grid == rb.grid:
            raise FleetError(f"{fleet.where}: {ra.grid}: its spacing places {line.removeprefix('robots ')}: widen it")
        spec.warnings.append(line)
    if spec.placements:  # every rule finds room in the first worlds' draws, or the file is refused
        from batchsim.variation import Bound, Variation

        worlds = np.arange(PLACEMENT_CHECK)
        placed = Bound(Variation(placements=spec.placements), spec.mjmodel).placed(worlds, np.zeros_like(worlds))
        if not placed.all():
            rule = spec.placements[0].where
            raise FleetError(
                f"{rule}: found no spot min_distance from the others for every robot in {int((~placed).sum())} of "
                f"the first {PLACEMENT_CHECK} worlds: widen the area or lower min_distance"
            )
    logging.getLogger("batchsim").debug("fleet %s: %d robots", fleet.where, len(spec.robots))
    return spec
