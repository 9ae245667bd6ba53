"""A Variation resolved against one model, and the draws it makes per world.

`Bound(variation, m)` checks every name, column and bound against the model (one
VariationError naming the file and key), then `draw(worlds, counters)` gives each listed world
its values of every varied field: `(n, *field shape)` float64, from the nominal model, the
entries applied in order. A value depends only on (seed, the entry's stream, the world's
number, its counter, the element): world 731 of a fleet of 8192 draws what world 731 alone
(`--worlds 1 --world-offset 731`) does.
"""

from __future__ import annotations

import dataclasses
import difflib

import mujoco
import numpy as np

from batchsim.variation import counter_rng
from batchsim.variation.spec import (
    Distribution,
    Draw,
    FieldVariation,
    Operation,
    Per,
    Placement,
    Variation,
    VariationError,
)

_OBJ = mujoco.mjtObj
# an MjModel field's objects, by the field's prefix (dof_ and qpos0 are named by their joints)
_PREFIX = {
    "body_": (_OBJ.mjOBJ_BODY, "nbody"),
    "jnt_": (_OBJ.mjOBJ_JOINT, "njnt"),
    "geom_": (_OBJ.mjOBJ_GEOM, "ngeom"),
    "site_": (_OBJ.mjOBJ_SITE, "nsite"),
    "cam_": (_OBJ.mjOBJ_CAMERA, "ncam"),
    "light_": (_OBJ.mjOBJ_LIGHT, "nlight"),
    "mat_": (_OBJ.mjOBJ_MATERIAL, "nmat"),
    "pair_": (_OBJ.mjOBJ_PAIR, "npair"),
    "eq_": (_OBJ.mjOBJ_EQUALITY, "neq"),
    "tendon_": (_OBJ.mjOBJ_TENDON, "ntendon"),
    "actuator_": (_OBJ.mjOBJ_ACTUATOR, "nu"),
    "sensor_": (_OBJ.mjOBJ_SENSOR, "nsensor"),
}
# values that must stay positive where the model has them positive, and those that must stay >= 0
_POSITIVE = frozenset({"body_mass", "body_inertia"})
_NON_NEGATIVE = frozenset(
    {
        "geom_friction",
        "dof_damping",
        "dof_armature",
        "dof_frictionloss",
        "jnt_stiffness",
        "actuator_kp",
        "actuator_kv",
    }
)
_NDOF = {int(mujoco.mjtJoint.mjJNT_FREE): 6, int(mujoco.mjtJoint.mjJNT_BALL): 3}
_NQPOS = {int(mujoco.mjtJoint.mjJNT_FREE): 7, int(mujoco.mjtJoint.mjJNT_BALL): 4}
_SLIDING = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
_START_STREAM = "start_pose"
#: candidates a random placement draws for each robot before taking the farthest
PLACEMENT_TRIES = 64
_UNIT = Draw(Distribution.UNIFORM, 0.0, 1.0)


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n, 4) Hamilton products a * b of (w, x, y, z) quaternions."""
    aw, ax, ay, az = a.T
    bw, bx, by, bz = b.T
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=1,
    )


@dataclasses.dataclass(frozen=True)
class Target:
    """Where one entry writes in one MjModel field: rows (objects), columns (None: a 1-D
    field), and the sign a drawn value takes (a gain stored negated in biasprm)."""

    field: str
    rows: np.ndarray
    cols: np.ndarray | None
    sign: float = 1.0


@dataclasses.dataclass(frozen=True)
class Entry:
    """One `fields` entry resolved: its targets (the first is the entry's own field; a gain's
    first is where kp or kv lives in gainprm or biasprm), the shape of one world's draw
    (objects, columns; (1, 1) per world) and its stream."""

    spec: FieldVariation
    targets: tuple[Target, ...]
    shape: tuple[int, int]
    stream: np.uint64


def nominal(m: mujoco.MjModel, field: str) -> np.ndarray:
    """A model field's values, a float64 copy (`opt.<name>` for an option: gravity is (3,))."""
    if field.startswith("opt."):
        return np.array(getattr(m.opt, field[4:]), np.float64).reshape(-1)
    return np.array(getattr(m, field), np.float64)


class Bound:
    """A Variation checked against `m`: the fields it varies and how to draw them.

    Attributes:
      variation: what it was made from.
      fields: every MjModel field a draw writes, in order: those the entries name, then the
        derived ones (body_subtreemass follows body_mass, as mj_setConst computes it).
      where: each field's entry as messages name it (`file: randomize.fields[2]`).
      entries: the `fields` entries resolved (Entry), in order.
    """

    def __init__(self, variation: Variation, m: mujoco.MjModel):
        self.variation = variation
        self._m = m
        self._nominal: dict[str, np.ndarray] = {}
        self.where: dict[str, str] = {}  # each field's first entry (file: randomize.fields[i]), for messages
        self.entries = [self._resolve(e) for e in variation.fields]
        self.fields = list(self._nominal)
        self._subtree = "body_mass" in self._nominal
        if self._subtree and "body_subtreemass" not in self._nominal:
            self.fields.append("body_subtreemass")
            self.where["body_subtreemass"] = self.where["body_mass"] + " (body_subtreemass follows body_mass)"
        self._start = None if variation.start_pose is None else self._resolve_start()
        self._placements = [(p, self._free_joints(p)) for p in variation.placements]

    # --- drawing ---
    def draw(self, worlds: np.ndarray, counters: np.ndarray) -> dict[str, np.ndarray]:
        """Every varied field's values in the listed worlds.

        Args:
          worlds: (n,) the worlds' numbers in the fleet (offset included).
          counters: (n,) each world's draw number (0 at start; a reset that redraws adds 1).

        Returns:
          field -> (n, *field shape) float64, for every name in `fields`.
        """
        worlds = np.asarray(worlds, np.int64)
        n = len(worlds)
        out = {f: np.broadcast_to(v, (n, *v.shape)).copy() for f, v in self._nominal.items()}
        for entry, values in zip(self.entries, self.entry_draws(worlds, counters), strict=True):
            op = entry.spec.operation
            for target in entry.targets:
                array = out[target.field]
                v = values  # (n, objects or 1, columns or 1)
                if target.cols is not None and v.shape[2] != len(target.cols):
                    v = v[:, :, :1]  # an `also` field: the object's one draw over all its columns
                if target.field.startswith("opt."):
                    index: tuple = (slice(None), target.cols)
                    v = v[:, 0, :]
                elif target.cols is None:
                    index = (slice(None), target.rows)
                    v = v[:, :, 0]
                else:
                    index = (slice(None), target.rows[:, None], target.cols[None, :])
                if op is Operation.SCALE:
                    array[index] *= v
                elif op is Operation.ADD:
                    array[index] += target.sign * v
                else:
                    array[index] = target.sign * v
        if self._subtree:
            out["body_subtreemass"] = subtree_mass(self._m, out["body_mass"])
        return out

    def entry_draws(self, worlds: np.ndarray, counters: np.ndarray) -> list[np.ndarray]:
        """What each entry draws for the listed worlds before it changes a field (the factor of a
        `scale`, the offset of an `add`, the value of a `set`): per entry `(n, *entry.shape)`."""
        worlds = np.asarray(worlds, np.int64)
        return [
            self._sample(e.spec.draw, e.stream, worlds, counters, e.shape[0] * e.shape[1]).reshape(len(worlds), *e.shape)
            for e in self.entries
        ]

    def start_qpos(self, worlds: np.ndarray, counters: np.ndarray, qpos: np.ndarray) -> np.ndarray | None:
        """(n, nq) start positions: `qpos` (nq,) with each listed world's noise added to the
        varied joints, clipped to their ranges; None without start-pose noise."""
        if self._start is None and not self._placements:
            return None
        n = len(worlds)
        worlds = np.asarray(worlds, np.int64)
        out = np.broadcast_to(np.asarray(qpos, np.float64), (n, len(qpos))).copy()
        if self._start is not None:
            adr, low, high = self._start
            pose = self.variation.start_pose
            assert pose is not None
            noise = self._sample(pose.draw, counter_rng.stream_id(_START_STREAM), worlds, counters, len(adr))
            out[:, adr] = np.clip(out[:, adr] + noise, low, high)
        for placement, adr in self._placements:
            self._place(placement, adr, worlds, counters, out)
        return out

    def placed(self, worlds: np.ndarray, counters: np.ndarray) -> np.ndarray:
        """(n,) bool: whether every placement rule found room for its robots in each world (a
        world where one did not has some closer than min_distance)."""
        qpos = np.zeros(self._m.nq)
        ok = np.ones(len(worlds), bool)
        for placement, adr in self._placements:
            ok &= self._place(placement, adr, np.asarray(worlds, np.int64), counters, np.tile(qpos, (len(worlds), 1)))
        return ok

    def _place(
        self, placement: Placement, adr: np.ndarray, worlds: np.ndarray, counters: np.ndarray, out: np.ndarray
    ) -> np.ndarray:
        """Each world's robots of `placement` into `out` (n, nq): PLACEMENT_TRIES candidates a
        robot, the first at least min_distance from those placed before it (else the farthest);
        (n,) bool, whether every robot of a world found such a spot."""
        n, k, tries = len(worlds), len(adr), PLACEMENT_TRIES
        u = self._sample(_UNIT, counter_rng.stream_id(f"placement {placement.where}"), worlds, counters, k * tries * 3)
        u = u.reshape(n, k, tries, 3)
        x0, y0, x1, y1 = placement.area
        xy = np.stack([x0 + (x1 - x0) * u[..., 0], y0 + (y1 - y0) * u[..., 1]], axis=-1)  # (n, k, tries, 2)
        yaw = placement.yaw[0] + (placement.yaw[1] - placement.yaw[0]) * u[..., 2]
        chosen = np.zeros((n, k), np.intp)
        ok = np.ones(n, bool)
        rows = np.arange(n)
        for r in range(1, k):  # robot r against the robots placed before it, every world at once
            placed = xy[rows[:, None], np.arange(r)[None, :], chosen[:, :r]]  # (n, r, 2)
            gaps = np.linalg.norm(xy[:, r, :, None, :] - placed[:, None, :, :], axis=-1).min(axis=2)  # (n, tries)
            fits = gaps >= placement.min_distance
            first = np.where(fits.any(axis=1), fits.argmax(axis=1), gaps.argmax(axis=1))
            ok &= fits.any(axis=1)
            chosen[:, r] = first
        pick = (rows[:, None], np.arange(k)[None, :], chosen)
        for r, a in enumerate(adr):
            out[:, a : a + 2] = xy[pick][:, r]
            half = 0.5 * yaw[pick][:, r]
            turn = np.stack([np.cos(half), np.zeros(n), np.zeros(n), np.sin(half)], axis=1)
            out[:, a + 3 : a + 7] = _quat_mul(turn, out[:, a + 3 : a + 7])
        return ok

    def _free_joints(self, placement: Placement) -> np.ndarray:
        m = self._m
        free = {int(m.jnt_qposadr[j]) for j in range(m.njnt) if int(m.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_FREE)}
        for adr in placement.qposadr:
            if adr not in free:
                raise VariationError(f"{placement.where}: qpos[{adr}] is no free joint's: only a floating base is placed")
        return np.array(placement.qposadr, np.int64)

    def _sample(
        self, draw: Draw, stream: np.uint64, worlds: np.ndarray, counters: np.ndarray, size: int
    ) -> np.ndarray:
        """(n, size) float64 draws."""
        keys = counter_rng.world_keys(self.variation.seed, stream, worlds)
        bits = counter_rng.bits(keys, np.asarray(counters), counter_rng.element_offsets(size))
        if draw.distribution is Distribution.NORMAL:
            values = draw.a + draw.b * counter_rng.normal64(bits)
        elif draw.distribution is Distribution.LOGUNIFORM:
            low, high = np.log(draw.a), np.log(draw.b)
            values = np.exp(low + (high - low) * counter_rng.uniform64(bits))
        else:
            values = draw.a + (draw.b - draw.a) * counter_rng.uniform64(bits)
        if draw.bounds is not None:
            np.clip(values, *draw.bounds, out=values)
        return values

    # --- resolving names against the model ---
    def _resolve(self, spec: FieldVariation) -> Entry:
        m = self._m
        if spec.field in ("actuator_kp", "actuator_kv"):
            targets = _gain_targets(m, spec, self._rows(spec, "actuator_gainprm"))
            rows = targets[0].rows
            primary_cols = None
        else:
            values = self._field(spec.field, spec.where + ".field")
            rows = self._rows(spec, spec.field)
            primary_cols = self._columns(spec, values)
            targets = [Target(spec.field, rows, primary_cols)]
        ncol = 1 if primary_cols is None else len(primary_cols)
        for other in spec.also:
            values = self._field(other, spec.where + ".also")
            if ncol != 1:
                raise VariationError(
                    f"{spec.where}.also: {other} follows a draw per object; give one column of {spec.field}"
                )
            if object_kind(m, other) != object_kind(m, spec.field):
                raise VariationError(
                    f"{spec.where}.also: {other} does not hold the objects {spec.field} holds"
                )
            targets.append(Target(other, rows, None if values.ndim == 1 else np.arange(values.shape[1])))
        for target in targets:
            self._nominal.setdefault(target.field, nominal(m, target.field))
            self.where.setdefault(target.field, spec.where)
        self._check_sign(spec, targets)
        shape = (len(rows), ncol) if spec.per is Per.OBJECT else (1, 1)
        return Entry(spec, tuple(targets), shape, counter_rng.stream_id(spec.stream))

    def _field(self, name: str, where: str) -> np.ndarray:
        m = self._m
        if name.startswith("opt."):
            value = getattr(m.opt, name[4:], None)
            if value is None or isinstance(value, int) or np.asarray(value).dtype.kind != "f":
                raise VariationError(
                    f"{where}: {name} is not a numeric MuJoCo option (opt.gravity, opt.wind, ...)"
                )
            return nominal(m, name)
        value = getattr(m, name, None)
        if not isinstance(value, np.ndarray) or value.dtype.kind != "f" or not value.size:
            numeric = [
                f
                for f in dir(m)
                if isinstance(getattr(m, f, None), np.ndarray) and getattr(m, f).dtype.kind == "f"
            ]
            close = difflib.get_close_matches(name, numeric, n=3)
            hint = f" (did you mean {', '.join(close)}?)" if close else ""
            raise VariationError(f"{where}: {name} is not a numeric MjModel field of this model{hint}")
        return value

    def _rows(self, spec: FieldVariation, field: str) -> np.ndarray:
        m = self._m
        kind = object_kind(m, field)
        count = len(nominal(m, field)) if not field.startswith("opt.") else 1
        if spec.names is None:
            return np.arange(count)
        if kind is None:
            raise VariationError(f"{spec.where}.names: {field} does not belong to named objects")
        if field.startswith("dof_") or field == "qpos0":
            joints = [self._id(_OBJ.mjOBJ_JOINT, name, spec.where + ".names") for name in spec.names]
            adr, width = (m.jnt_dofadr, _NDOF) if field.startswith("dof_") else (m.jnt_qposadr, _NQPOS)
            return np.concatenate(
                [np.arange(adr[j], adr[j] + width.get(int(m.jnt_type[j]), 1)) for j in joints]
            )
        return np.array([self._id(kind, name, spec.where + ".names") for name in spec.names])

    def _id(self, kind: mujoco.mjtObj, name: str, where: str) -> int:
        i = mujoco.mj_name2id(self._m, kind, name)
        if i < 0:
            what = kind.name[len("mjOBJ_") :].lower()
            raise VariationError(f"{where}: no {what} named {name!r} in the model")
        return int(i)

    @staticmethod
    def _columns(spec: FieldVariation, values: np.ndarray) -> np.ndarray | None:
        if values.ndim == 1 and not spec.field.startswith("opt."):
            if spec.columns is not None:
                raise VariationError(
                    f"{spec.where}.columns: {spec.field} has one value per object, no columns"
                )
            return None
        width = values.shape[-1]
        cols = np.arange(width) if spec.columns is None else np.array(spec.columns)
        if cols.max() >= width:
            raise VariationError(
                f"{spec.where}.columns: {spec.field} has {width} columns (0..{width - 1}), got {int(cols.max())}"
            )
        return cols

    def _check_sign(self, spec: FieldVariation, targets: list[Target]) -> None:
        """Refuse an entry that can make a positive value non-positive, or a non-negative one negative."""
        low, _ = spec.draw.support()
        for target in targets:
            name = spec.field if spec.field in _NON_NEGATIVE else target.field
            if name not in _POSITIVE and name not in _NON_NEGATIVE:
                continue
            values = self._nominal[target.field]
            if values.ndim == 1 and target.field.startswith("opt."):
                values = values[None]
            chosen = values[target.rows] if target.cols is None else values[target.rows][:, target.cols]
            chosen = np.abs(chosen) if target.sign < 0 else chosen
            if spec.operation is Operation.SCALE:
                least = (chosen * low)[chosen > 0]
            elif spec.operation is Operation.ADD:
                least = (chosen + low)[chosen > 0] if name in _POSITIVE else chosen + low
            else:
                least = np.array([low])
            strict = name in _POSITIVE
            bad = least <= 0 if strict else least < 0
            if least.size and bad.any():
                what = "non-positive" if strict else "negative"
                raise VariationError(
                    f"{spec.where}.{spec.operation.value}: {spec.draw.describe()} can make {target.field} {what} "
                    f"(down to {float(least.min()):g}); bound the draw"
                )

    def _resolve_start(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        m = self._m
        pose = self.variation.start_pose
        assert pose is not None
        if pose.joints is None:
            joints = [j for j in range(m.njnt) if int(m.jnt_type[j]) in _SLIDING]
            if not joints:
                raise VariationError(f"{pose.where}: the model has no hinge or slide joint to vary")
        else:
            joints = [self._id(_OBJ.mjOBJ_JOINT, name, pose.where + ".joints") for name in pose.joints]
            for name, j in zip(pose.joints, joints, strict=True):
                if int(m.jnt_type[j]) not in _SLIDING:
                    raise VariationError(f"{pose.where}.joints: {name} is not a hinge or slide joint")
        j = np.array(joints)
        limited = m.jnt_limited[j].astype(bool)
        low = np.where(limited, m.jnt_range[j, 0], -np.inf)
        high = np.where(limited, m.jnt_range[j, 1], np.inf)
        return m.jnt_qposadr[j].astype(np.int64), low, high


def object_kind(m: mujoco.MjModel, field: str) -> mujoco.mjtObj | None:
    """The kind of object a field's rows are (joints for dof_ and qpos0), or None."""
    if field.startswith("dof_") or field == "qpos0":
        return _OBJ.mjOBJ_JOINT
    for prefix, (kind, count) in _PREFIX.items():
        if field.startswith(prefix) and len(np.atleast_1d(getattr(m, field))) == getattr(m, count):
            return kind
    return None


def _gain_targets(m: mujoco.MjModel, spec: FieldVariation, rows: np.ndarray) -> list[Target]:
    """Where a position actuator's kp or kv lives: kp in gainprm[0] and -biasprm[1], kv in
    -biasprm[2] (and in gainprm[0] of a velocity actuator, whose biasprm[1] is 0)."""
    gain, bias = m.actuator_gainprm, m.actuator_biasprm
    affine = int(mujoco.mjtBias.mjBIAS_AFFINE)
    kp_rows, kv_velocity, kv_position = [], [], []
    for a in rows:
        name = mujoco.mj_id2name(m, _OBJ.mjOBJ_ACTUATOR, int(a)) or f"#{a}"
        if int(m.actuator_biastype[a]) != affine:
            if spec.names is not None:
                raise VariationError(
                    f"{spec.where}.names: actuator {name!r} is not a position or velocity actuator"
                )
            continue
        position = bias[a, 1] != 0 and np.isclose(bias[a, 1], -gain[a, 0])
        velocity = bias[a, 1] == 0 and np.isclose(bias[a, 2], -gain[a, 0])
        if spec.field == "actuator_kp":
            if position:
                kp_rows.append(a)
            elif spec.names is not None:
                raise VariationError(
                    f"{spec.where}.names: actuator {name!r} is not a position actuator (no kp)"
                )
        elif velocity:
            kv_velocity.append(a)
        elif position:
            kv_position.append(a)
    targets: list[Target] = []
    if kp_rows:
        r = np.array(kp_rows)
        targets += [
            Target("actuator_gainprm", r, np.array([0])),
            Target("actuator_biasprm", r, np.array([1]), -1.0),
        ]
    if kv_velocity:
        r = np.array(kv_velocity)
        targets += [
            Target("actuator_gainprm", r, np.array([0])),
            Target("actuator_biasprm", r, np.array([2]), -1.0),
        ]
    if kv_position:
        targets.append(Target("actuator_biasprm", np.array(kv_position), np.array([2]), -1.0))
    if not targets:
        raise VariationError(f"{spec.where}.field: the model has no actuator with a {spec.field[9:]} to vary")
    if spec.per is Per.OBJECT and len(targets) > 2:
        raise VariationError(
            f"{spec.where}: vary kv of position and velocity actuators in separate entries (names:)"
        )
    return targets


def subtree_mass(m: mujoco.MjModel, mass: np.ndarray) -> np.ndarray:
    """(n, nbody) each body's mass plus its descendants', from (n, nbody) masses (mj_setConst's sum)."""
    out = np.array(mass, np.float64)
    for b in range(m.nbody - 1, 0, -1):
        out[:, m.body_parentid[b]] += out[:, b]
    return out
