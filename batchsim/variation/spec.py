"""The randomization file: what varies per world, parsed and checked without a model.

```yaml
randomize:
  seed: 0                    # world i's draw depends only on (seed, i)
  redraw_on_reset: false     # true: a world draws afresh each time it is reset
  fields:
    - field: body_mass       # an MjModel field by its MuJoCo name, opt.<name>, actuator_kp or actuator_kv
      also: [body_inertia]   # fields scaled by the same draw, object for object
      names: [link1, link2]  # the objects, by name (default: all of the field's objects)
      columns: [0]           # the columns of a field with several (default: all)
      scale: {uniform: [0.8, 1.2]}   # scale, add or set; uniform, normal or loguniform; bounds: [lo, hi]
      per: object            # object: a draw per object and column (default); world: one per world
  start_pose:
    joints: [joint1]         # hinge and slide joints by name (default: all of them)
    add: {normal: [0.0, 0.05]}       # around the keyframe, clipped to the joint's range
```

Strings live here only: `parse` turns them into `Operation`, `Distribution` and `Per` members
and numbers, and every fault is one `VariationError` naming the file and the key.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from batchsim.types import AnyCase

#: fields whose per-world values would break what every world shares
FIXED_FIELDS = {
    "opt.timestep": "every world steps with one timestep (the control period is a whole number of them)"
}
#: batchsim's names for the position actuators' gains, beside MuJoCo's own fields
GAIN_FIELDS = ("actuator_kp", "actuator_kv")


class VariationError(ValueError):
    """A randomization file or mapping that cannot be used: one line, naming the file and key."""


class Operation(AnyCase, enum.Enum):
    """How a draw changes a field's nominal value."""

    SCALE = "scale"  # nominal * draw
    ADD = "add"  # nominal + draw
    SET = "set"  # draw


class Distribution(AnyCase, enum.Enum):
    UNIFORM = "uniform"  # [low, high]
    NORMAL = "normal"  # [mean, stddev]
    LOGUNIFORM = "loguniform"  # [low, high], low > 0: uniform in log space


class Per(AnyCase, enum.Enum):
    OBJECT = "object"  # a draw per object and column
    WORLD = "world"  # one draw per world for every object and column listed


@dataclasses.dataclass(frozen=True)
class Draw:
    """One distribution, with optional bounds that clip what it draws.

    Attributes:
      distribution: its kind.
      a, b: low and high (uniform, loguniform), or mean and standard deviation (normal).
      bounds: (low, high) the draws are clipped to, or None.
    """

    distribution: Distribution
    a: float
    b: float
    bounds: tuple[float, float] | None = None

    def support(self) -> tuple[float, float]:
        """The least and greatest value a draw can take."""
        if self.distribution is Distribution.NORMAL:
            low, high = (-math.inf, math.inf) if self.b > 0 else (self.a, self.a)
        else:
            low, high = self.a, self.b
        if self.bounds is not None:
            low, high = max(low, self.bounds[0]), min(high, self.bounds[1])
        return low, high

    def describe(self) -> str:
        name = self.distribution.value
        text = f"{name}({self.a:g}, {self.b:g})"
        if self.bounds is not None:
            text += f" in [{self.bounds[0]:g}, {self.bounds[1]:g}]"
        return text


@dataclasses.dataclass(frozen=True)
class FieldVariation:
    """One entry of `fields`: a field (and those in `also`) changed per world by one draw.

    Attributes:
      field: the MjModel field (`opt.<name>` for an option), or actuator_kp / actuator_kv.
      also: fields changed by the same draw, object for object (body_inertia beside body_mass).
      names: the objects by name; None: every object.
      columns: the columns of a multi-column field; None: every column.
      operation, draw: how the nominal value changes, and what is drawn.
      per: a draw per object and column, or one per world.
      where: the file and key, for messages.
      stream: the draw's stream name: the field and its entry's count among that field's entries.
    """

    field: str
    also: tuple[str, ...]
    names: tuple[str, ...] | None
    columns: tuple[int, ...] | None
    operation: Operation
    draw: Draw
    per: Per
    where: str
    stream: str


@dataclasses.dataclass(frozen=True)
class StartPose:
    """Noise around the start pose, per hinge or slide joint.

    Attributes:
      joints: the joints by name; None: every hinge and slide joint.
      draw: added to each joint's start position (rad or m), clipped to a limited joint's range.
    """

    joints: tuple[str, ...] | None
    draw: Draw
    where: str


@dataclasses.dataclass(frozen=True)
class Placement:
    """Robots placed at random per world by their free joints (a fleet file's `random:` rule,
    batchsim.fleet): x, y uniform in `area`, a yaw uniform in `yaw` turning each robot's start
    orientation, at least `min_distance` apart; z and the rest of the pose as the start pose.

    Attributes:
      qposadr: each free joint's address in qpos.
      area: (xmin, ymin, xmax, ymax), metres.
      yaw: (low, high), radians.
      min_distance: metres between any two of these robots' free-joint origins.
      where: the rule, for messages.
    """

    qposadr: tuple[int, ...]
    area: tuple[float, float, float, float]
    yaw: tuple[float, float]
    min_distance: float
    where: str


@dataclasses.dataclass(frozen=True)
class Variation:
    """What varies per world: parsed from a file or mapping by `parse`.

    Attributes:
      seed: the draws' seed.
      redraw_on_reset: whether a reset world draws afresh (its n-th reset draws the n-th time).
      fields: the field entries, applied in order.
      start_pose: noise around the start pose, or None.
      source: the file (or "<mapping>"), for messages.
      placements: robots placed at random per world (a fleet file's, not the YAML's).
    """

    seed: int = 0
    redraw_on_reset: bool = False
    fields: tuple[FieldVariation, ...] = ()
    start_pose: StartPose | None = None
    source: str = "<mapping>"
    placements: tuple[Placement, ...] = ()

    @property
    def active(self) -> bool:
        return bool(self.fields) or self.start_pose is not None or bool(self.placements)

    def field_names(self) -> list[str]:
        """Every field an entry names (also included), in order, once each."""
        names: list[str] = []
        for entry in self.fields:
            for name in (entry.field, *entry.also):
                if name not in names:
                    names.append(name)
        return names


_TOP_KEYS = ("seed", "redraw_on_reset", "fields", "start_pose")
_FIELD_KEYS = ("field", "also", "names", "columns", "per", *(op.value for op in Operation))
_DRAW_KEYS = (*(d.value for d in Distribution), "bounds")


def load(source: str | Path | Mapping[str, Any] | Variation) -> Variation:
    """A Variation from a YAML file (its `randomize:` block, or the file's whole mapping), a
    parsed mapping, or a Variation as it is. VariationError naming file and key otherwise."""
    if isinstance(source, Variation):
        return source
    if isinstance(source, Mapping):
        return parse(source, "<mapping>")
    from batchsim.model.params import read_yaml  # the project's one YAML loader

    path = Path(source)
    try:
        document = read_yaml(path)
    except ValueError as e:  # ParamsError: a missing file or malformed YAML, named
        raise VariationError(str(e)) from None
    if not isinstance(document, Mapping):
        raise VariationError(
            f"{path}: a randomization file holds a mapping (`randomize:`), got {type(document).__name__}"
        )
    return parse(document, str(path))


def parse(document: Mapping[str, Any], source: str) -> Variation:
    """A Variation from a mapping: its `randomize:` block if it has one, else itself."""
    block = document.get("randomize", document)
    where = f"{source}: randomize"  # a mapping without the key is the block itself
    if not isinstance(block, Mapping):
        raise VariationError(f"{where}: must be a mapping of {', '.join(_TOP_KEYS)}, got {block!r}")
    _known(block, _TOP_KEYS, where)
    seed = block.get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise VariationError(f"{where}.seed: must be a non-negative integer, got {seed!r}")
    redraw = block.get("redraw_on_reset", False)
    if not isinstance(redraw, bool):
        raise VariationError(f"{where}.redraw_on_reset: must be true or false, got {redraw!r}")
    entries = block.get("fields", [])
    if not isinstance(entries, Sequence) or isinstance(entries, str):
        raise VariationError(f"{where}.fields: must be a list of field entries, got {entries!r}")
    fields: list[FieldVariation] = []
    seen: dict[str, int] = {}
    for i, entry in enumerate(entries):
        parsed = _field(entry, f"{where}.fields[{i}]", seen)
        fields.append(parsed)
    start = block.get("start_pose")
    start_pose = None if start is None else _start_pose(start, f"{where}.start_pose")
    return Variation(int(seed), redraw, tuple(fields), start_pose, source)


def _known(block: Mapping[str, Any], keys: Sequence[str], where: str) -> None:
    unknown = [k for k in block if k not in keys]
    if unknown:
        raise VariationError(f"{where}: unknown key {unknown[0]!r} (known: {', '.join(keys)})")


def _names(value: Any, where: str, what: str) -> tuple[str, ...]:
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, Sequence) or not value or not all(isinstance(v, str) and v for v in value):
        raise VariationError(f"{where}: must be a non-empty list of {what}, got {value!r}")
    return tuple(value)


def _field(entry: Any, where: str, seen: dict[str, int]) -> FieldVariation:
    if not isinstance(entry, Mapping):
        raise VariationError(
            f"{where}: must be a mapping with `field` and one of scale, add, set; got {entry!r}"
        )
    _known(entry, _FIELD_KEYS, where)
    field = entry.get("field")
    if not isinstance(field, str) or not field:
        raise VariationError(
            f"{where}.field: must name a MuJoCo model field (body_mass, geom_friction, ...), got {field!r}"
        )
    if field in FIXED_FIELDS:
        raise VariationError(f"{where}.field: {field} cannot vary per world: {FIXED_FIELDS[field]}")
    also = () if "also" not in entry else _names(entry["also"], f"{where}.also", "field names")
    for name in also:
        if name in FIXED_FIELDS or name in GAIN_FIELDS:
            raise VariationError(f"{where}.also: {name} cannot follow another field's draw")
    names = None if "names" not in entry else _names(entry["names"], f"{where}.names", "object names")
    columns = None
    if "columns" in entry:
        raw = entry["columns"]
        raw = [raw] if isinstance(raw, int) else raw
        if (
            not isinstance(raw, Sequence)
            or not raw
            or not all(isinstance(c, int) and not isinstance(c, bool) and c >= 0 for c in raw)
        ):
            raise VariationError(
                f"{where}.columns: must be a list of column indices (0, 1, ...), got {entry['columns']!r}"
            )
        columns = tuple(raw)
    ops = [op for op in Operation if op.value in entry]
    if len(ops) != 1:
        raise VariationError(
            f"{where}: give exactly one of scale, add, set (got {', '.join(o.value for o in ops) or 'none'})"
        )
    operation = ops[0]
    try:
        per = Per(entry.get("per", "object"))
    except ValueError:
        raise VariationError(f"{where}.per: must be object or world, got {entry.get('per')!r}") from None
    draw = _draw(entry[operation.value], f"{where}.{operation.value}")
    if operation is Operation.SCALE and draw.support()[0] < 0:
        raise VariationError(
            f"{where}.scale: a scale must stay >= 0, but {draw.describe()} reaches {draw.support()[0]:g}"
        )
    count = seen.get(field, 0)
    seen[field] = count + 1
    return FieldVariation(field, also, names, columns, operation, draw, per, where, f"{field}#{count}")


def _pair(value: Any, where: str) -> tuple[float, float]:
    if not isinstance(value, Sequence) or isinstance(value, str) or len(value) != 2:
        raise VariationError(f"{where}: must be two numbers [a, b], got {value!r}")
    try:
        a, b = float(value[0]), float(value[1])
    except (TypeError, ValueError):
        raise VariationError(f"{where}: must be two numbers [a, b], got {value!r}") from None
    if not (math.isfinite(a) and math.isfinite(b)):
        raise VariationError(f"{where}: must be finite, got {value!r}")
    return a, b


def _draw(value: Any, where: str) -> Draw:
    if not isinstance(value, Mapping):
        raise VariationError(f"{where}: must be a mapping such as {{uniform: [0.8, 1.2]}}, got {value!r}")
    _known(value, _DRAW_KEYS, where)
    kinds = [d for d in Distribution if d.value in value]
    if len(kinds) != 1:
        raise VariationError(f"{where}: give exactly one of uniform, normal, loguniform")
    kind = kinds[0]
    a, b = _pair(value[kind.value], f"{where}.{kind.value}")
    if kind is Distribution.NORMAL:
        if b < 0:
            raise VariationError(f"{where}.normal: [mean, stddev] needs stddev >= 0, got {b:g}")
    elif a > b:
        raise VariationError(f"{where}.{kind.value}: low {a:g} > high {b:g}")
    if kind is Distribution.LOGUNIFORM and a <= 0:
        raise VariationError(f"{where}.loguniform: low must be > 0, got {a:g}")
    bounds = None
    if "bounds" in value:
        bounds = _pair(value["bounds"], f"{where}.bounds")
        if bounds[0] > bounds[1]:
            raise VariationError(f"{where}.bounds: low {bounds[0]:g} > high {bounds[1]:g}")
    return Draw(kind, a, b, bounds)


def _start_pose(value: Any, where: str) -> StartPose:
    if not isinstance(value, Mapping):
        raise VariationError(f"{where}: must be a mapping with `add` (and optional `joints`), got {value!r}")
    _known(value, ("joints", "add"), where)
    if "add" not in value:
        raise VariationError(f"{where}: needs `add`: the noise added to each joint's start position")
    joints = None if "joints" not in value else _names(value["joints"], f"{where}.joints", "joint names")
    return StartPose(joints, _draw(value["add"], f"{where}.add"), where)
