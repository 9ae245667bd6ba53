"""MJX's jitted programs, compiled once per (model, nworld, device, determinism, held base, varied
fields) and shared by every engine of that key in the process: a control period (the substeps in
`lax.scan` or `lax.fori_loop`, then each world's failure check), a masked reset, the readings'
gather, and the device path's state and command programs.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from batchsim.backends.device import FIELD_SHIFT, INDEX_SHIFT, MAX_INDEX
from batchsim.backends.mjx.fields import fingerprint, with_fields
from batchsim.model import RobotSpec, StateColumn
from batchsim.plugins.base_velocity import HELD_DOFS
from batchsim.types import MAX_COMMAND, HeldBase, StateSource, Status

_CACHE_SIZE = 8  # compiled programs kept per process, by (model, nworld, device)


class Programs(NamedTuple):
    """The jitted programs of one (model, nworld, device, determinism, varied fields)."""

    # (d, nstep: int, fields[, held (nworld, 3)]) -> (d, (nworld, ncolumn + nsensordata + 1)
    # float32): one control period, `fields` the varied model fields' per-world values (field ->
    # (nworld, *shape); {}: none), `held` the base velocity's target with one
    # (batchsim.plugins.base_velocity); the readings after the period (before it, for a world that
    # failed), then its failure code
    period: Callable[..., Any]
    reset: Callable[..., Any]  # (d, d0, mask) -> d
    read: Callable[..., Any]  # (qpos, qvel, qfrc_actuator, sensordata) -> (nworld, ncolumn + nsensordata)


_PROGRAMS: OrderedDict[tuple[Any, ...], Programs] = OrderedDict()


def programs(
    mx: mjx.Model,
    spec: RobotSpec,
    columns: list[StateColumn],
    nworld: int,
    device: jax.Device,
    deterministic: bool,
    held: HeldBase | None = None,
    varied: tuple[str, ...] = (),
) -> Programs:
    """Compile (once per key) what one system runs.

    A period is one upload of ctrl and time, one program and one download: the readings
    (state columns, sensordata) come back packed in one float32 array with each world's
    failure code as a last column. On a GPU each separate jit call or download costs a few hundred
    microseconds of host time during which the device idles: at 16 worlds read()'s own
    program and downloads were ~5% of a period. ctrl is put into the Data before the call
    rather than passed to the program, which measured ~1.6 ms a period slower on an H200
    (benchmarks/mjx_period.py, "raw+ctrl").
    """
    key = (fingerprint(spec.mjmodel), tuple(c.name for c in columns), nworld, device, deterministic, held, varied)
    if key in _PROGRAMS:
        _PROGRAMS.move_to_end(key)
        return _PROGRAMS[key]
    shared = jax.vmap(mjx.step, in_axes=(None, 0))
    per_world = jax.vmap(lambda f, d: mjx.step(with_fields(mx, f), d))
    m = spec.mjmodel
    offset = dict(zip(StateSource, np.cumsum([0, m.nq, m.nv, m.nv]), strict=True))
    take = np.array([offset[c.source] + c.index for c in columns], dtype=np.int32)

    def read(qpos: jax.Array, qvel: jax.Array, qfrc: jax.Array, sensordata: jax.Array):
        # these four arrays, not the whole Data: a jit call costs per argument (~80 leaves in Data)
        fields = jnp.concatenate([qpos, qvel, qfrc, sensordata], axis=1)
        return jnp.concatenate([fields[:, take], sensordata], axis=1)

    def check(d: mjx.Data) -> jax.Array:
        """Each world's failure code (batchsim.backends.device): the first bad entry of qpos,
        then qvel, then qacc, as MuJoCo checks them."""
        code = jnp.zeros(nworld, jnp.int32)
        for field, x in ((3, d.qacc), (2, d.qvel), (1, d.qpos)):  # the last written wins: qpos first
            bad = jnp.isnan(x) | (jnp.abs(x) > MAX_COMMAND)
            index = jnp.minimum(jnp.argmax(bad, axis=1), MAX_INDEX).astype(jnp.int32)
            here = int(Status.DIVERGED) | (field << FIELD_SHIFT) | (index << INDEX_SHIFT)
            code = jnp.where(bad.any(axis=1), here, code)
        return code.astype(jnp.float32)  # exact: codes stay below 2**24

    def period(d: mjx.Data, nstep: Any, fields: dict, target: jax.Array | None = None) -> tuple[mjx.Data, jax.Array]:
        start = read(d.qpos, d.qvel, d.qfrc_actuator, d.sensordata)
        step = (lambda d: per_world(fields, d)) if fields else (lambda d: shared(mx, d))
        substep = step if target is None else _holding(step, held, d.qpos, target)
        if isinstance(nstep, int):  # a static trip count: XLA runs the loop without asking the host
            d = jax.lax.scan(lambda d, _: (substep(d), None), d, None, length=nstep)[0]
        else:
            d = jax.lax.fori_loop(0, nstep, lambda _, d: substep(d), d)
        code = check(d)
        # a world that failed reads as it did before this period (the contract's rule)
        readings = jnp.where((code != 0)[:, None], start, read(d.qpos, d.qvel, d.qfrc_actuator, d.sensordata))
        return d, jnp.concatenate([readings, code[:, None]], axis=1)

    def reset(d: mjx.Data, d0: mjx.Data, mask: jax.Array) -> mjx.Data:
        def pick(x, x0):
            return jnp.where(mask.reshape((-1,) + (1,) * (x.ndim - 1)), x0[None], x)

        return jax.tree.map(pick, d, d0)

    # XLA:GPU sums with atomics, whose order varies from run to run; its deterministic mode
    # does not (at a cost in speed). The CPU is deterministic either way.
    options = {"xla_gpu_deterministic_ops": True} if deterministic and device.platform == "gpu" else None
    if device.platform == "cpu":
        # XLA:CPU runs loops on the host anyway: nstep as data, one program for every nstep
        jitted = _float32(jax.jit(period, donate_argnums=0))

        def run(d: mjx.Data, nstep: int, fields: dict, *target: jax.Array) -> tuple[mjx.Data, jax.Array]:
            return jitted(d, np.int32(nstep), fields, *target)
    else:
        # on an accelerator a data-dependent trip count costs a device-to-host sync per
        # substep; a static one does not, so nstep is compiled in (once per control rate)
        run = _float32(jax.jit(period, static_argnums=1, donate_argnums=0, compiler_options=options))

    programs = Programs(
        period=run,
        reset=jax.jit(reset, donate_argnums=0, compiler_options=options),
        read=jax.jit(read, compiler_options=options),
    )
    _PROGRAMS[key] = programs
    while len(_PROGRAMS) > _CACHE_SIZE:
        _PROGRAMS.popitem(last=False)
    return programs


def _holding(step: Callable[..., Any], held: Any, qpos: jax.Array, target: jax.Array) -> Callable[..., Any]:
    """A substep that first writes the held base velocity into qvel (batchsim.plugins.base_velocity's
    world_velocity, inlined): `target` (nworld, 3) body-frame vx, vy, wz, rotated by the base's
    orientation in `qpos` (the period's start); NaN rows leave the physics alone."""
    qposadr, dofadr = held.qposadr, held.dofadr
    w, x, y, z = (qpos[:, qposadr + 3 + k] for k in range(4))
    s = 2.0 / (w * w + x * x + y * y + z * z)
    vx, vy, wz = target[:, 0], target[:, 1], target[:, 2]
    value = jnp.stack(
        [
            (1.0 - s * (y * y + z * z)) * vx + s * (x * y - w * z) * vy,
            s * (x * y + w * z) * vx + (1.0 - s * (x * x + z * z)) * vy,
            wz,
        ],
        axis=1,
    )
    dofs = dofadr + np.array(HELD_DOFS)
    free = jnp.isnan(value)

    def substep(d: mjx.Data) -> mjx.Data:
        return step(d.replace(qvel=d.qvel.at[:, dofs].set(jnp.where(free, d.qvel[:, dofs], value))))

    return substep


def _float32(program: Callable[..., Any]) -> Callable[..., Any]:
    """`program`, traced and run with float32 matrix products.

    JAX's default on NVIDIA GPUs since Ampere multiplies float32 matrices in TF32 (10-bit
    mantissa). Measured on an H200 against the cpu backend, a humanoid's joints then part by
    2.3e-4 rad after 10 steps and 8e-2 after 100, against 6e-7 and 2.3e-4 with float32
    products (the parity test caught it). The precision is part of JAX's compile-cache key,
    so this costs nothing per call beyond entering the context.
    """

    def call(*args: Any) -> Any:
        with jax.default_matmul_precision("highest"):
            return program(*args)

    return call


def device_programs(programs: Programs, spec: RobotSpec, sign: np.ndarray) -> tuple[Any, Any]:
    """The device path's jitted programs: the state interfaces gathered and times `sign` (nstate,),
    and a command (nworld, ncommand) written into ctrl, parked worlds' rows zero."""
    nstate = len(sign)
    signs = jnp.asarray(sign)
    actuator = jnp.asarray(np.array([c.actuator_id for c in spec.commands], np.int32))
    read = programs.read

    def state(qpos: jax.Array, qvel: jax.Array, qfrc: jax.Array, sensordata: jax.Array) -> jax.Array:
        return read(qpos, qvel, qfrc, sensordata)[:, :nstate] * signs

    def write(ctrl: jax.Array, command: jax.Array, parked: jax.Array) -> jax.Array:
        ctrl = ctrl.at[:, actuator].set(command.astype(ctrl.dtype))
        return jnp.where(parked[:, None], jnp.zeros_like(ctrl), ctrl)

    return jax.jit(state), jax.jit(write)
