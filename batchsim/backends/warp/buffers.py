"""MuJoCo Warp's contact and constraint buffers: their first size, from a short CPU rollout of
the model; what overflowed and which option's buffers hold it; how far to grow them, whether
the memory allows it, and the grown Data with every world carried over.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Any

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp

from batchsim.backends.device import DEVICE_ARRAYS

_O = mjw.OverflowType
# Buffers that, once full, drop contacts or constraints: the world's results are wrong.
# ITERATIONS / LS_ITERATIONS only say the solver stopped early, as MuJoCo's does.
BUFFER_OVERFLOWS = int(
    _O.NEFC
    | _O.NJMAX_NNZ
    | _O.BROADPHASE
    | _O.NARROWPHASE
    | _O.CCD
    | _O.HFIELD
    | _O.CONTACT_MATCH
    | _O.NVMAX
    | _O.EPA_HORIZON
    | _O.TACTILE
)
# what filled up, for the log; and which option's buffers hold it (None: none that can grow)
OVERFLOWS = {
    _O.BROADPHASE: ("contact candidates", "nconmax"),
    _O.NARROWPHASE: ("contacts", "nconmax"),
    _O.CCD: ("convex-collision contacts", "nconmax"),
    _O.NEFC: ("constraint rows", "njmax"),
    _O.NJMAX_NNZ: ("constraint Jacobian non-zeros", "njmax"),
    _O.HFIELD: ("height-field contacts per geom pair (lower the height field's resolution)", None),
    _O.CONTACT_MATCH: ("contact-sensor matches (MuJoCo Warp's opt.contact_sensor_maxmatch)", None),
    _O.NVMAX: ("island degrees of freedom (nvmax)", None),
    _O.EPA_HORIZON: ("the convex-collision EPA horizon", None),
    _O.TACTILE: ("tactile-sensor pairs", None),
}
GROWS = {"nconmax": 0, "njmax": 0}
for _kind, (_what, _option) in OVERFLOWS.items():
    if _option is not None:
        GROWS[_option] |= int(_kind)

# the whole integration state, carried into grown buffers
_INTEGRATION = int(mjw.State.PHYSICS | mjw.State.USER | mjw.State.WARMSTART)  # no PLUGIN in Warp

# growth: at least this factor, at most that, per re-allocation
_GROW_MIN, _GROW_MAX = 2.0, 8.0
_MEMORY_MARGIN = 0.9  # of the free memory a grown Data may take
_MAX_ELEMENTS = 2**31 - 1  # Warp indexes arrays with 32-bit integers

# buffer sizing from a CPU rollout
_SIZING_SECONDS = 2.0
_SIZING_MAX_STEPS = 2000
_HEADROOM = 2.0


def rollout_sizes(m: mujoco.MjModel, *, seed: int = 0) -> tuple[int, int]:
    """(nconmax, njmax) for `m`: the most contacts seen in a short CPU rollout, with headroom.

    The rollout runs up to 2 s of simulated time twice, once passive and once under random
    in-range controls, and takes the most contacts any step had. nconmax is that with 2x
    headroom; njmax is the most constraint rows those contacts and every limit, friction
    and equality of the model can make at once.
    """
    d = mujoco.MjData(m)
    nsteps = max(1, min(_SIZING_MAX_STEPS, math.ceil(_SIZING_SECONDS / m.opt.timestep)))
    lo, hi = np.full(m.nu, -1.0), np.full(m.nu, 1.0)
    limited = m.actuator_ctrllimited.astype(bool)
    lo[limited], hi[limited] = m.actuator_ctrlrange[limited, 0], m.actuator_ctrlrange[limited, 1]
    rng = np.random.default_rng(seed)
    ncon = ne = 0
    for excite in (False, True):
        mujoco.mj_resetData(m, d)
        for i in range(nsteps):
            if excite and i % 10 == 0:
                d.ctrl[:] = rng.uniform(lo, hi)
            mujoco.mj_step(m, d)
            if d.warning[int(mujoco.mjtWarning.mjWARN_BADQACC)].number:
                break  # the model blew up under random controls: what came before counts
            ncon = max(ncon, d.ncon)
            ne = max(ne, int(d.ne))
    nconmax = int(math.ceil(_HEADROOM * ncon)) + 4
    # contact rows: pyramidal cones take 2 (condim - 1) rows, elliptic condim, frictionless 1
    condim = int(m.geom_condim.max()) if m.ngeom else 1
    if m.npair:
        condim = max(condim, int(m.pair_dim.max()))
    elliptic = m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    rows = 1 if condim == 1 else (condim if elliptic else 2 * (condim - 1))
    nfriction = int((m.dof_frictionloss > 0).sum() + (m.tendon_frictionloss > 0).sum())
    nlimit = int(m.jnt_limited.sum() + m.tendon_limited.sum())
    njmax = ne + nfriction + nlimit + nconmax * rows
    return nconmax, max(njmax, 1)


def grown(now: int, need: int) -> int:
    """The new size for a buffer of `now` that needed `need`: at least twice, more where the
    counters ask for more (with a quarter on top), at most _GROW_MAX times."""
    want = max(math.ceil(_GROW_MIN * max(now, 1)), math.ceil(1.25 * need))
    return int(min(want, math.ceil(_GROW_MAX * max(now, 1))))


def data_size(d: Any, con_ratio: float, j_ratio: float) -> tuple[float, int]:
    """(bytes, largest element count) of a Data like `d` with its contact buffers scaled by
    con_ratio and its constraint buffers by j_ratio: an estimate from its arrays' shapes."""
    con_dims = {d.naconmax, d.naccdmax}
    j_dims = {d.njmax, d.njmax_pad, d.njmax_nnz}
    total, largest = 0.0, 0

    def visit(obj: Any) -> None:
        nonlocal total, largest
        for value in vars(obj).values():
            if isinstance(value, wp.array):
                scale = 1.0
                for dim in value.shape:
                    if dim in con_dims:
                        scale *= con_ratio
                    elif dim in j_dims:
                        scale *= j_ratio
                total += value.capacity * scale
                largest = max(largest, math.ceil(value.size * scale))
            elif dataclasses.is_dataclass(value) and not isinstance(value, type):
                visit(value)

    visit(d)
    return total, largest


def memory_for_data(device: Any, max_data_bytes: float | None) -> float:
    """Bytes a grown Data may take: max_data_bytes, else a margin under what is free."""
    if max_data_bytes is not None:
        return float(max_data_bytes)
    if device.is_cuda:
        return _MEMORY_MARGIN * device.free_memory
    try:  # Warp's CPU device: the host's available memory (Linux)
        return _MEMORY_MARGIN * os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return math.inf


def growable(bits: int) -> dict[str, int]:
    """The options whose buffers hold what overflowed (`bits`, of BUFFER_OVERFLOWS), each with
    its bits; empty where none of it can grow."""
    return {option: bits & mask for option, mask in GROWS.items() if bits & mask}


def plan_growth(
    d: Any, nworld: int, now: dict[str, int], grows: dict[str, int], limit: float, limited_by: str
) -> tuple[dict[str, int] | None, str]:
    """The sizes (nconmax, njmax per world) to grow the `grows` options of `now` to, and "";
    or None and why not, where even the least growth needs more than `limit` bytes (`limited_by`
    names that limit). Ample growth first; then only what MuJoCo Warp's counters ask."""
    # MuJoCo Warp's counters go on counting past the buffers: what the last step needed
    need = {
        "nconmax": math.ceil(max(int(d.ncollision.numpy()[0]), int(d.nacon.numpy()[0])) / nworld),
        "njmax": int(d.nefc.numpy().max()),
    }
    plans = []
    for ample in (True, False):
        size = dict(now)
        for option in grows:
            lo = max(now[option] + 1, need[option])
            size[option] = grown(now[option], need[option]) if ample else lo
        if size not in plans:
            plans.append(size)
    for size in plans:
        nbytes, elements = data_size(
            d, size["nconmax"] / max(now["nconmax"], 1), size["njmax"] / max(now["njmax"], 1)
        )
        if nbytes <= limit and elements <= _MAX_ELEMENTS:
            return size, ""
    size = plans[-1]
    return None, (
        f"growing {' and '.join(f'{o} to {size[o]}' for o in grows)} per world needs "
        f"{nbytes / 2**30:.2f} GiB, more than {limited_by} allows ({limit / 2**30:.2f} GiB)"
    )


def grown_names(bits: int, grows: dict[str, int]) -> str:
    """What filled up in the `grows` options' buffers, for the log: "contacts (nconmax)"."""
    return " and ".join(
        " and ".join(what for kind, (what, option) in OVERFLOWS.items() if option == o and bits & int(kind))
        + f" ({o})"
        for o in grows
    )


def overflow_reason(bits: int, cannot_grow: str) -> str:
    """A failed world's overflow bits as words, with why its buffers could not grow (if they could)."""
    kinds = [(what, option) for kind, (what, option) in OVERFLOWS.items() if bits & int(kind)]
    said = "; ".join(what + (f" ({option})" if option else "") for what, option in kinds)
    if any(option for _, option in kinds) and cannot_grow:
        said += f"; {cannot_grow}"
    return said or "a buffer overflowed"


def grown_data(mw: Any, m: mujoco.MjModel, old: Any, nworld: int, nconmax: int, njmax: int) -> Any:
    """A new Data of `nworld` worlds with these buffers, every world's integration state carried
    over from `old` (on the current device); the arrays device_arrays() hands out
    (DEVICE_ARRAYS) are `old`'s own objects, values kept, so users may hold them."""
    state = wp.zeros((nworld, mujoco.mj_stateSize(m, _INTEGRATION)), dtype=wp.float32)
    mjw.get_state(mw, old, state, _INTEGRATION)
    new = mjw.make_data(m, nworld=nworld, nconmax=nconmax, njmax=njmax)
    mjw.set_state(mw, new, state, _INTEGRATION)
    for field in DEVICE_ARRAYS:  # same values; keep the arrays users may hold
        setattr(new, field, getattr(old, field))
    return new
