"""The batched search: a cross-entropy method over a box, written once, pure NumPy, seeded.

Each round every candidate (a world) holds one value per parameter, drawn uniformly within the
current box; `tell(values, errors)` keeps the `elite` share with the least error and narrows
the box to their mean plus and minus their spread (the half-width of a uniform distribution
with their standard deviation, widened by `inflate`), never wider than it was and never
outside the starting box:

    search = BoxSearch(low=[0.5, 0.5], high=[2.0, 2.0], elite=0.1, seed=0)
    for _ in range(4):
        values = search.sample(256)            # or the worlds' own draws (batchsim.variation)
        search.tell(values, error_of(values))  # (256,) one error per candidate
    search.centre, search.best                 # the elite's mean, the best candidate seen

The calibration draws its candidates through the `randomize:` machinery (each world's draw
depends only on the seed, the world and the round); `sample` is the same box drawn with
NumPy's generator, for using the search on its own.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np


@dataclasses.dataclass(frozen=True)
class Round:
    """One round's outcome.

    Attributes:
      low, high: (k,) the box the round's candidates were drawn in.
      best_error: the least error of the round; elite_error: the elite's mean error.
      best: (k,) the round's best candidate; centre: (k,) the elite's mean.
      candidates: how many were told, finite: how many of them had a finite error.
    """

    low: np.ndarray
    high: np.ndarray
    best_error: float
    elite_error: float
    best: np.ndarray
    centre: np.ndarray
    candidates: int
    finite: int


class BoxSearch:
    """A cross-entropy search over the box [low, high] (k parameters).

    Args:
      low, high: (k,) the starting box; every later box lies inside it.
      elite: the share of a round's candidates the box narrows to (at least 2 of them).
      inflate: the elite's spread is widened by this before it becomes the next box, so that
        a narrow elite drawn by chance does not shut out the answer.
      min_width: no side narrows below this share of its starting width.
      seed: `sample`'s seed (round r draws from (seed, r)).
    """

    def __init__(
        self,
        low: np.ndarray,
        high: np.ndarray,
        *,
        elite: float = 0.1,
        inflate: float = 1.5,
        min_width: float = 0.01,
        seed: int = 0,
    ):
        self.start_low = np.array(low, np.float64).reshape(-1)
        self.start_high = np.array(high, np.float64).reshape(-1)
        if self.start_low.shape != self.start_high.shape:
            raise ValueError(f"low and high must have one shape, got {self.start_low.shape} and {self.start_high.shape}")
        if not (np.isfinite(self.start_low).all() and np.isfinite(self.start_high).all()):
            raise ValueError("the box must be finite")
        if (self.start_low > self.start_high).any():
            raise ValueError("low must be <= high")
        if not 0 < elite <= 1:
            raise ValueError(f"elite must be in (0, 1], got {elite:g}")
        self.elite, self.inflate, self.min_width, self.seed = float(elite), float(inflate), float(min_width), int(seed)
        self.low, self.high = self.start_low.copy(), self.start_high.copy()
        self.rounds: list[Round] = []
        self.best = 0.5 * (self.low + self.high)
        self.best_error = math.inf

    @property
    def centre(self) -> np.ndarray:
        """(k,) the last elite's mean (before any round: the box's middle)."""
        return self.rounds[-1].centre.copy() if self.rounds else 0.5 * (self.low + self.high)

    def sample(self, n: int) -> np.ndarray:
        """(n, k) candidates uniform in the current box, from (seed, round)."""
        rng = np.random.default_rng([self.seed, len(self.rounds)])
        return self.low + (self.high - self.low) * rng.random((n, len(self.low)))

    def tell(self, values: np.ndarray, errors: np.ndarray) -> Round:
        """Narrow the box to the elite of `values` (n, k) by `errors` (n,) (NaN or inf: worst)."""
        values = np.asarray(values, np.float64).reshape(len(errors), -1)
        errors = np.where(np.isfinite(errors), np.asarray(errors, np.float64), math.inf)
        order = np.argsort(errors, kind="stable")
        finite = int(np.isfinite(errors).sum())
        if not finite:
            raise ValueError("every candidate failed (no finite error): nothing to narrow to")
        count = min(finite, max(2, math.ceil(self.elite * len(errors))))
        elite = values[order[:count]]
        centre = elite.mean(axis=0)
        half_was = 0.5 * (self.high - self.low)
        floor = 0.5 * self.min_width * (self.start_high - self.start_low)
        half = np.clip(self.inflate * math.sqrt(3.0) * elite.std(axis=0), floor, np.maximum(half_was, floor))
        done = Round(
            self.low.copy(),
            self.high.copy(),
            float(errors[order[0]]),
            float(errors[order[:count]].mean()),
            values[order[0]].copy(),
            centre,
            len(errors),
            finite,
        )
        if done.best_error < self.best_error:
            self.best_error, self.best = done.best_error, done.best.copy()
        # the next box: around the elite, inside the starting box (shifted in rather than cut)
        low = np.maximum(centre - half, self.start_low)
        high = np.minimum(centre + half, self.start_high)
        width = np.minimum(2 * half, self.start_high - self.start_low)
        self.low = np.where(low + width > self.start_high, self.start_high - width, low)
        self.high = np.where(high - width < self.start_low, self.start_low + width, high)
        self.low = np.maximum(self.low, self.start_low)
        self.high = np.minimum(self.high, self.start_high)
        self.rounds.append(done)
        return done


def quadratic_minimum(values: np.ndarray, errors: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray | None:
    """(k,) the least of a quadratic fitted by least squares to the squared `errors` (n,) of the
    better half of `values` (n, k), in [low, high]; None where too few candidates, or the fit
    is not a bowl (its Hessian not positive definite). An RMS error's square is near quadratic
    about its least, so this reads the answer off a round's worlds beyond the elite's mean."""
    values = np.asarray(values, np.float64)
    k = values.shape[1]
    keep = np.isfinite(errors)
    order = np.argsort(np.where(keep, errors, np.inf))[: max(keep.sum() // 2, 1)]
    nterm = 1 + k + k * (k + 1) // 2
    if len(order) < 2 * nterm:
        return None
    mid, half = 0.5 * (low + high), np.maximum(0.5 * (high - low), 1e-12)
    x = (values[order] - mid) / half
    iu = np.triu_indices(k)
    design = np.hstack([np.ones((len(x), 1)), x, (x[:, :, None] * x[:, None, :])[:, iu[0], iu[1]]])
    coef, *_ = np.linalg.lstsq(design, np.asarray(errors, np.float64)[order] ** 2, rcond=None)
    hessian = np.zeros((k, k))
    hessian[iu] = coef[1 + k :]
    hessian = hessian + hessian.T  # diagonal doubled: d2/dx2 of c x^2 is 2c
    try:
        np.linalg.cholesky(hessian)
        least = np.linalg.solve(hessian, -coef[1 : 1 + k])
    except np.linalg.LinAlgError:
        return None
    return np.clip(mid + half * least, low, high)
