"""What a variation draws, in words: `batchsim info --randomize FILE` and the bridge's diagnostics."""

from __future__ import annotations

import mujoco
import numpy as np

from batchsim.variation.draw import Bound, nominal, object_kind
from batchsim.variation.spec import Variation


def describe(variation: Variation) -> list[str]:
    """One line per entry: field(s), objects, columns, operation, distribution."""
    out = [
        f"seed {variation.seed}, {'a fresh draw at each reset' if variation.redraw_on_reset else 'drawn once per world'}"
    ]
    for e in variation.fields:
        fields = " + ".join((e.field, *e.also))
        objects = "all" if e.names is None else ", ".join(e.names)
        columns = "" if e.columns is None else f" columns {list(e.columns)}"
        out.append(
            f"{fields} [{objects}]{columns}: {e.operation.value} {e.draw.describe()}, a draw per {e.per.value}"
        )
    pose = variation.start_pose
    if pose is not None:
        joints = "every hinge and slide joint" if pose.joints is None else ", ".join(pose.joints)
        out.append(f"start pose [{joints}]: add {pose.draw.describe()}")
    return out


def changes(
    bound: Bound, m: mujoco.MjModel, params: dict[str, np.ndarray], row: int, most: int = 6
) -> list[str]:
    """One world's values (`row` of `params`, as Bound.draw or world_params give them) that differ
    from the model's own, a line per field: `body_mass link1=1.88 link2=2.00`, equal values
    once (`geom_friction[:, 0] 8 geoms=1.36`), at most `most` per field."""
    out: list[str] = []
    for field in bound.fields:
        value, base = params[field][row], nominal(m, field)
        changed = np.argwhere(value != base)
        if not len(changed):
            continue
        kind = object_kind(m, field)
        named = kind is not None and not field.startswith(("dof_", "qpos0"))
        values = [float(value[tuple(i)]) for i in changed]
        columns = sorted({int(i[1]) for i in changed}) if changed.shape[1] > 1 else []
        where = f"[:, {', '.join(map(str, columns))}]" if columns else ""
        if len(set(values)) == 1 and len(values) > 1:
            out.append(f"{field}{where} {len({int(i[0]) for i in changed})} rows={values[0]:.6g}")
            continue
        items = []
        for i, v in zip(changed[:most], values[:most], strict=False):
            label = (mujoco.mj_id2name(m, kind, int(i[0])) or f"#{i[0]}") if named else str(int(i[0]))
            items.append(f"{label}{''.join(f'[{c}]' for c in i[1:])}={v:.6g}")
        more = f" (+{len(values) - most})" if len(values) > most else ""
        out.append(f"{field} {' '.join(items)}{more}")
    return out
