"""Per-world model fields on MuJoCo Warp (batchsim.variation.worlds): its batched model arrays.

MuJoCo Warp's Model arrays whose spec starts with `*` (and those of its Option) take a leading
batch dimension, read as `field[worldid % field.shape[0]]` by every kernel: one row is the
shared model, `nworld` rows a value per world. A varied field gets its `nworld` rows on its
first draw, before the first period is captured; later draws (a reset that redraws) write
their worlds' rows of those same arrays in place (one upload of those rows and a scatter
kernel), so that captured graphs keep their pointers.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import mujoco
import numpy as np
import warp as wp
from mujoco_warp._src import types as mjw_types
from mujoco_warp._src import warp_util


@wp.kernel
def scatter_rows(src: wp.array(dtype=Any), rows: wp.array(dtype=wp.int32), dst: wp.array(dtype=Any)):
    """dst[rows[i]] = src[i]: a (nworld,) option array's redrawn worlds."""
    i = wp.tid()
    dst[rows[i]] = src[i]


@wp.kernel
def scatter_rows_2d(src: wp.array2d(dtype=Any), rows: wp.array(dtype=wp.int32), dst: wp.array2d(dtype=Any)):
    """dst[rows[i], j] = src[i, j]: a (nworld, nobject) model array's redrawn worlds."""
    i, j = wp.tid()
    dst[rows[i], j] = src[i, j]


def _batched(cls: type) -> frozenset[str]:
    return frozenset(
        f.name
        for f in dataclasses.fields(cls)
        if warp_util.is_array_spec(f.type) and getattr(f.type, "shape", ())[:1] == ("*",)
    )


_MODEL_FIELDS = _batched(mjw_types.Model)
_OPTION_FIELDS = frozenset(f"opt.{name}" for name in _batched(mjw_types.Option))


def batched_fields(m: mujoco.MjModel) -> frozenset[str]:
    """MuJoCo Warp's batched Model and Option arrays that mirror an MjModel field of `m`."""
    own = {f for f in _MODEL_FIELDS if isinstance(getattr(m, f, None), np.ndarray)}
    return frozenset(own | {f for f in _OPTION_FIELDS if hasattr(m.opt, f[4:])})


def set_world_fields(mw: Any, nworld: int, device: Any, worlds: np.ndarray, params: dict[str, np.ndarray]) -> None:
    """`params[field][worlds]` into the Warp Model `mw`'s arrays of those fields (field ->
    (nworld, *shape) float64), on `device`: a field's first draw gives it a row per world."""
    with wp.ScopedDevice(device):
        for field, values in params.items():
            owner, name = (mw.opt, field[4:]) if field.startswith("opt.") else (mw, field)
            array, redrawn = getattr(owner, name), worlds
            if array.shape[0] != nworld:  # the first draw: a row per world, before any capture
                host = values.astype(np.float32).reshape(len(values), *array.shape[1:], *_inner(array))
                setattr(owner, name, wp.array(host, dtype=array.dtype))
                redrawn = worlds[:1]  # and world 0's row scattered, to compile the redraw's kernel now
                array = getattr(owner, name)
            rows = values[redrawn].astype(np.float32).reshape(len(redrawn), *array.shape[1:], *_inner(array))
            src = wp.array(rows, dtype=array.dtype)
            index = wp.array(redrawn.astype(np.int32), dtype=wp.int32)
            kernel = scatter_rows if array.ndim == 1 else scatter_rows_2d
            wp.launch(kernel, dim=src.shape, inputs=[src, index], outputs=[array], device=device)


def _inner(array: wp.array) -> tuple[int, ...]:
    """The shape of one element of `array`: (3,) for a vec3, (3, 3) for a mat33, () for a scalar."""
    return tuple(getattr(array.dtype, "_shape_", None) or ())
