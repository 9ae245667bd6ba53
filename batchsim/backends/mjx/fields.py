"""Per-world model fields on MJX (batchsim.variation.worlds): a model vmapped over the worlds' values.

The period program (batchsim.backends.mjx.programs) takes the varied fields as an argument, field ->
(nworld, *shape) float32 on the device, and steps each world with `with_fields(mx, its row)`;
a redraw uploads the redrawn worlds' rows and scatters them on the device.
"""

from __future__ import annotations

import hashlib
from typing import Any

import jax
import mujoco
import numpy as np
from mujoco import mjx

_VARIABLE: dict[str, frozenset[str]] = {}  # variable_fields() per model fingerprint


def fingerprint(m: mujoco.MjModel) -> str:
    """A digest of everything in the model, so that equal models share compiled programs."""
    buffer = np.empty(mujoco.mj_sizeModel(m), np.uint8)
    mujoco.mj_saveModel(m, None, buffer)
    return hashlib.sha256(buffer.tobytes()).hexdigest()


@jax.jit
def scatter_rows(fields: dict, worlds: jax.Array, rows: dict) -> dict:
    return {f: fields[f].at[worlds].set(rows[f]) for f in fields}


def with_fields(mx: mjx.Model, fields: dict[str, jax.Array]) -> mjx.Model:
    """One world's model: `mx` with its values of the varied fields (`opt.<name>` for options)."""
    options = {k[4:]: v for k, v in fields.items() if k.startswith("opt.")}
    own = {k: v for k, v in fields.items() if not k.startswith("opt.")}
    return mx.replace(**own, opt=mx.opt.replace(**options)) if options else mx.replace(**own)


def variable_fields(m: mujoco.MjModel) -> frozenset[str]:
    """The fields MJX's Model holds as arrays of the MjModel's shape (a vmapped model takes them
    per world); its options likewise, as `opt.<name>`."""
    key = fingerprint(m)
    if key not in _VARIABLE:
        mx = mjx.put_model(m, device=jax.devices("cpu")[0], impl="jax")

        def arrays(owner: Any, source: Any, prefix: str) -> set[str]:
            return {
                prefix + name
                for name in dir(source)
                if not name.startswith("_")
                and isinstance(getattr(owner, name, None), jax.Array)
                and np.shape(getattr(owner, name)) == np.shape(getattr(source, name))
            }

        _VARIABLE[key] = frozenset(arrays(mx, m, "") | arrays(mx.opt, m.opt, "opt."))
    return _VARIABLE[key]
