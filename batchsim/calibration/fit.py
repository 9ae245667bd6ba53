"""The calibration's rounds: the search's box drawn over N worlds (batchsim.variation), the bag
replayed into them, the box narrowed to the worlds that tracked the real robot best; then the
model as it is ("before") and the fit ("after") replayed alone, joint by joint.

    fit = calibrate(bag, "arm", "ranges.yaml", "controllers.yaml", FitOptions(worlds=256, rounds=4))
    fit.fitted        (k,) each parameter's fitted draw (a factor of nominal for a scale)
    fit.before.rms    (1, njoint), fit.after.rms likewise

The fit is whichever of the last elite's mean, the best world seen and the least of a quadratic
fitted to the last round's errors tracks the real robot best alone.
Round r draws from the seed `seed * 1000 + r`, so a calibration repeats exactly.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from batchsim.calibration.bag import RealBag
from batchsim.calibration.parameters import (
    Parameter,
    fitted_block,
    fixed_variation,
    parameters,
    round_variation,
)
from batchsim.calibration.replay import WorldErrors, replay_worlds
from batchsim.variation import Variation, VariationError, load
from batchsim.variation.search import BoxSearch, Round, quadratic_minimum


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """How the search runs: `worlds` per round, `rounds`, the `elite` share, the `seed`, the backend."""

    worlds: int = 256
    rounds: int = 4
    elite: float = 0.1
    seed: int = 0
    backend: str = "cpu"


@dataclasses.dataclass
class Fit:
    """A calibration's outcome.

    Attributes:
      params: the searched parameters, in order.
      fitted: (k,) each one's fitted draw (a factor for a scale, an offset for an add, a value for a set).
      low, high: (k,) the last box.
      rounds: each round's outcome (search.Round).
      before, after: the model as it is, and as fitted, replayed alone (WorldErrors of one world).
      seconds: each round's wall time, then the final replays'.
      variation: the ranges searched (the given block).
      chosen: "elite mean", "best world" or "quadratic fit" (search.quadratic_minimum of the
        last round): where the fit came from.
    """

    params: list[Parameter]
    fitted: np.ndarray
    low: np.ndarray
    high: np.ndarray
    rounds: list[Round]
    before: WorldErrors
    after: WorldErrors
    seconds: list[float]
    variation: Variation
    chosen: str

    def fitted_values(self) -> np.ndarray:
        """(k,) the fitted values of the fields themselves (nominal times the factor, ...)."""
        return np.array([p.value(v) for p, v in zip(self.params, self.fitted.tolist(), strict=True)])

    def block(self) -> dict[str, Any]:
        """The `randomize:` block centred on the fit, with the last box's widths."""
        return fitted_block(self.params, self.fitted, self.low, self.high, self.variation.seed)


def calibrate(
    bag: RealBag,
    model: str | Path,
    ranges: str | Path | Mapping[str, Any] | Variation,
    controllers: str | Path | Mapping[str, Any],
    options: FitOptions,
    progress: Callable[[int, Round, BoxSearch, float], None] | None = None,
) -> Fit:
    """Fit `model`'s parameters that `ranges` varies to the real robot's `bag`.

    `progress(round, outcome, search, seconds)` is called after each round. VariationError for
    ranges that cannot be searched (unbounded, or no field entry); BagError for a bag the
    controllers refuse."""
    import batchsim

    variation = load(ranges)
    if not variation.fields:
        raise VariationError(f"{variation.source}: randomize.fields: calibration needs at least one field entry to fit")
    spec = batchsim.load(model)
    params = parameters(variation, spec.mjmodel)
    search = BoxSearch(
        np.array([p.low for p in params]), np.array([p.high for p in params]), elite=options.elite, seed=options.seed
    )
    seconds: list[float] = []
    for r in range(options.rounds):
        start = time.perf_counter()
        drawn = round_variation(params, search.low, search.high, options.seed * 1000 + r, variation.source)
        errors = replay_worlds(model, options.worlds, options.backend, drawn, bag, controllers)
        assert errors.draws is not None
        last = (errors.draws, errors.overall, search.low.copy(), search.high.copy())
        outcome = search.tell(errors.draws, errors.overall)
        seconds.append(time.perf_counter() - start)
        if progress is not None:
            progress(r, outcome, search, seconds[-1])
    start = time.perf_counter()
    before = replay_worlds(model, 1, options.backend, None, bag, controllers)
    candidates = {"elite mean": search.centre, "best world": search.best}
    bowl = quadratic_minimum(*last) if options.rounds else None
    if bowl is not None:
        candidates["quadratic fit"] = bowl
    alone = {
        name: replay_worlds(model, 1, options.backend, fixed_variation(params, values, variation.source), bag, controllers)
        for name, values in candidates.items()
    }
    chosen = min(alone, key=lambda name: float(alone[name].overall[0]))
    seconds.append(time.perf_counter() - start)
    return Fit(
        params, candidates[chosen], search.low, search.high, search.rounds, before, alone[chosen], seconds, variation, chosen
    )
