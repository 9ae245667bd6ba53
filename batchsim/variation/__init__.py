"""Per-world randomization: what varies per world (spec.py), each world's draw (draw.py), the
system's part that holds every world's draws and applies them at reset (worlds.py), what was
drawn, as a table (report.py), the seeded counter hash draws and sensor noise come from
(counter_rng.py), and the batched search that narrows draws toward a target (search.py: the
cross-entropy search of `batchsim calibrate`, batchsim.calibration).

    variation = batchsim.variation.load("randomize.yaml")   # or a mapping
    sim = batchsim.make("arm", 1024, "warp", randomize=variation)
    sim.world_params()["body_mass"]                          # (1024, nbody)

World i's draw depends only on the seed and i (counter-based, as sensor noise is), so a run
repeats, and a world's conditions do not change with the fleet's size. The contract applies
the draws (worlds.py) through each engine's batched model fields.
"""

from batchsim.variation.draw import Bound, nominal, subtree_mass
from batchsim.variation.spec import (
    Distribution,
    Draw,
    FieldVariation,
    Operation,
    Per,
    Placement,
    StartPose,
    Variation,
    VariationError,
    load,
    parse,
)

__all__ = [
    "Bound",
    "Distribution",
    "Draw",
    "FieldVariation",
    "Operation",
    "Per",
    "Placement",
    "StartPose",
    "Variation",
    "VariationError",
    "load",
    "nominal",
    "parse",
    "subtree_mass",
]
