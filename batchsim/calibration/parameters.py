"""The search's parameters: a `randomize:` block's entries split into one value per varied
object (and column), each with the range its draw spans; a round's Variation from a box; the
values each world drew; and the fitted block written back as YAML.

An entry `{field: body_mass, names: [link2, link3], scale: {uniform: [0.5, 1.5]}}` becomes two
parameters, `body_mass link2` and `body_mass link3`, each a factor of its nominal mass searched
in [0.5, 1.5]. A round draws them through the same machinery a fleet's randomization uses
(batchsim.variation), one entry per parameter, so world i's candidate depends only on the
round's seed and i. An entry drawn once per world (`per: world`), or over objects without
names, stays one parameter for all its objects.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import mujoco
import numpy as np

from batchsim.variation import Distribution, Draw, FieldVariation, Operation, Per, Variation, VariationError
from batchsim.variation.draw import Bound, nominal, object_kind


@dataclasses.dataclass(frozen=True)
class Parameter:
    """One searched value.

    Attributes:
      entry: the `randomize:` entry it comes from (its field, also, operation).
      obj: the object's name; None: every object of the entry by one draw.
      column: the column of a multi-column field; None: the entry's own columns.
      low, high: the range its draw spans in the given block.
      distribution: UNIFORM or LOGUNIFORM (how each round draws within its box).
      nominal: the model's own value of the field for this object (the first, where obj is None).
    """

    entry: FieldVariation
    obj: str | None
    column: int | None
    low: float
    high: float
    distribution: Distribution
    nominal: float

    @property
    def operation(self) -> Operation:
        return self.entry.operation

    @property
    def key(self) -> str:
        """The object as reports name it: its name, `name[column]`, or `*` for every object."""
        name = self.obj if self.obj is not None else "*"
        return name if self.column is None else f"{name}[{self.column}]"

    @property
    def label(self) -> str:
        return f"{self.entry.field} {self.key}"

    def value(self, draw: float) -> float:
        """The field's value a draw gives (a scale's factor times nominal, ...)."""
        if self.operation is Operation.SCALE:
            return self.nominal * draw
        if self.operation is Operation.ADD:
            return self.nominal + draw
        return draw

    def neutral(self) -> float:
        """The draw that leaves the model as it is: 1 for a scale, 0 for an add, nominal for a set."""
        return {Operation.SCALE: 1.0, Operation.ADD: 0.0, Operation.SET: self.nominal}[self.operation]


def parameters(variation: Variation, m: mujoco.MjModel) -> list[Parameter]:
    """The parameters of every field entry of `variation` resolved against `m`. VariationError
    for an entry whose range is unbounded (a normal draw without bounds)."""
    bound = Bound(variation, m)
    out: list[Parameter] = []
    for entry in bound.entries:
        spec = entry.spec
        low, high = spec.draw.support()
        if not (math.isfinite(low) and math.isfinite(high)):
            raise VariationError(
                f"{spec.where}.{spec.operation.value}: calibration searches a bounded range: give uniform or "
                f"loguniform, or bounds: [low, high], not {spec.draw.describe()}"
            )
        kind = Distribution.LOGUNIFORM if spec.draw.distribution is Distribution.LOGUNIFORM else Distribution.UNIFORM
        target = entry.targets[0]
        values = nominal(m, target.field)
        if target.field.startswith("opt."):
            values = values[None]
        rows = target.rows if not target.field.startswith("opt.") else np.zeros(1, np.intp)
        gain = spec.field in ("actuator_kp", "actuator_kv")  # one value per actuator, whatever column holds it
        cols = [None] if target.cols is None or gain else target.cols.tolist()
        names = _row_names(m, spec.field, target.field, rows)
        nominals = [
            [target.sign * float(values[r] if values.ndim == 1 else values[r, target.cols[0] if c is None else c]) for c in cols]
            for r in rows.tolist()
        ]
        split = spec.per is Per.OBJECT and None not in names and len(set(names)) == len(names)
        if not split:
            out.append(Parameter(spec, None, None, low, high, kind, nominals[0][0]))
            continue
        for r, name in enumerate(names):
            for c, col in enumerate(cols):
                out.append(Parameter(spec, name, col, low, high, kind, nominals[r][c]))
    return out


def _row_names(m: mujoco.MjModel, field: str, target: str, rows: np.ndarray) -> list[str | None]:
    """The name of the object of each row (a dof's joint for dof_ fields); None where unnamed."""
    if target.startswith("opt."):
        return [None]
    kind = object_kind(m, target if field not in ("actuator_kp", "actuator_kv") else "actuator_gainprm")
    if kind is None:
        return [None] * len(rows)
    if target.startswith("dof_"):
        rows = m.dof_jntid[rows]
    return [mujoco.mj_id2name(m, kind, int(r)) or None for r in rows]


def round_variation(params: Sequence[Parameter], low: np.ndarray, high: np.ndarray, seed: int, source: str) -> Variation:
    """The Variation that draws each parameter within [low, high] (k,): one entry each."""
    fields = []
    for p, lo, hi in zip(params, low.tolist(), high.tolist(), strict=True):
        fields.append(_entry(p, Draw(p.distribution, lo, hi)))
    return Variation(seed=int(seed), fields=tuple(fields), source=source)


def _entry(p: Parameter, draw: Draw) -> FieldVariation:
    spec = p.entry
    return dataclasses.replace(
        spec,
        names=spec.names if p.obj is None else (p.obj,),
        columns=spec.columns if p.column is None else (p.column,),
        draw=draw,
        per=Per.WORLD if p.obj is None else Per.OBJECT,
        where=f"{spec.where} ({p.key})",
        stream=f"calibrate {p.label}",
    )


def drawn(bound: Bound, nworld: int, counters: np.ndarray) -> np.ndarray:
    """(nworld, k) what each world drew per parameter, from a round's bound Variation."""
    draws = bound.entry_draws(np.arange(nworld), counters)
    return np.stack([d[:, 0, 0] for d in draws], axis=1)


def fixed_variation(params: Sequence[Parameter], values: np.ndarray, source: str) -> Variation:
    """The Variation that gives every world exactly `values` (k,)."""
    return round_variation(params, values, values, 0, source)


def fitted_block(
    params: Sequence[Parameter], fitted: np.ndarray, low: np.ndarray, high: np.ndarray, seed: int
) -> dict[str, Any]:
    """The `randomize:` block centred on `fitted` (k,): each parameter's range the final box's
    width around its fitted value, inside the range it was searched in."""
    fields = []
    for p, value, lo, hi in zip(params, fitted.tolist(), low.tolist(), high.tolist(), strict=True):
        half = 0.5 * (hi - lo)
        a, b = max(p.low, value - half), min(p.high, value + half)
        if p.distribution is Distribution.LOGUNIFORM and a <= 0:
            a = min(value, p.low) if p.low > 0 else value
        entry: dict[str, Any] = {"field": p.entry.field}
        if p.entry.also:
            entry["also"] = list(p.entry.also)
        names = p.entry.names if p.obj is None else (p.obj,)
        if names is not None:
            entry["names"] = list(names)
        columns = p.entry.columns if p.column is None else (p.column,)
        if columns is not None:
            entry["columns"] = list(columns)
        entry[p.operation.value] = {p.distribution.value: [_round(a), _round(b)]}
        if p.obj is None:  # searched as one value for every object
            entry["per"] = "world"
        fields.append(entry)
    return {"randomize": {"seed": int(seed), "fields": fields}}


def _round(value: float) -> float:
    return float(f"{value:.6g}")
