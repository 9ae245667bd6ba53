"""The `mjx` backend: MuJoCo XLA (`mujoco.mjx`, its JAX implementation) in float32.

The worlds are one `jax.vmap` of `mjx.step`; one control period is one jitted call that
runs the `nstep` substeps in `lax.scan` on the device and then checks every world, with
the Data buffers donated so that XLA steps them in place. On a GPU or TPU a program is
compiled once per (model, nworld, nstep): a static trip count spares a device-to-host sync
per substep. On JAX's CPU device, where loops run on the host anyway, `nstep` is data
(`lax.fori_loop`) and one program per (model, nworld) serves every nstep, which keeps the
test suite's compile time down. Programs are shared by every system of one model and size
in the process. write() only fills a host buffer, uploaded once by the next step(); the
readings and status flags come back in one packed download, which read() then copies out
without touching the device: one upload, one launch and one download per control period,
as the warp backend's captured graph does.

On a GPU, XLA sums with atomics whose order varies from run to run, so two runs of the same
commands agree only to float32 rounding; `deterministic=True` compiles with XLA's
deterministic ops for bitwise-repeatable runs, at a cost in speed (benchmarks/RESULTS.md).
On the CPU device results are bitwise repeatable either way.

A world whose qpos, qvel or qacc goes non-finite or beyond MuJoCo's mjMAXVAL gets
DIVERGED and is frozen as on the other backends: it reads as it did before the step() in
which it failed while, on the device, it is parked (reset, ctrl held at zero) until
`reset()` lists it. The period program itself picks those readings: for a world that failed
it returns the readings it gathered before the substeps, for the others those after, in the
same download. MJX's JAX implementation sizes contacts and constraints statically from the
model, so its buffers cannot overflow and OVERFLOW is never set here.

Time is float64 on the host (JAX computes in float32 unless x64 is switched on process-wide):
each period adds the timestep to every world's clock as mj_step does, and the device's
float32 `time` is set from it when the period starts.

`device_arrays()` hands out the live JAX arrays (zero copy, DLPack-capable) for users who
stay on the device.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import batch as mjbatch
from mujoco import mjx

from batchsim.backends import footprint
from batchsim.backends.device import (
    DEVICE_ARRAYS,
    FIELD_SHIFT,
    INDEX_SHIFT,
    MAX_INDEX,
    DeviceSystem,
    code_status,
)
from batchsim.backends.host_sensors import HostSensors
from batchsim.backends.mjx_device import MjxDeviceIO
from batchsim.backends.mjx_fields import MjxFields, fingerprint, with_fields
from batchsim.base_velocity import HELD_DOFS
from batchsim.hardware import MAX_COMMAND, Status, StepFailures
from batchsim.model import RobotSpec, StateColumn
from batchsim.sensors import Camera, Lidar
from batchsim.types import StateSource

_CACHE_SIZE = 8  # compiled programs kept per process, by (model, nworld, device)


class _Programs(NamedTuple):
    """The jitted programs of one (model, nworld, device, determinism, varied fields)."""

    # (d, nstep: int, fields[, held (nworld, 3)]) -> (d, (nworld, ncolumn + nsensordata + 1)
    # float32): one control period, `fields` the varied model fields' per-world values (field ->
    # (nworld, *shape); {}: none), `held` the base velocity's target with one
    # (batchsim.base_velocity); the readings after the period (before it, for a world that
    # failed), then its failure code
    period: Callable[..., Any]
    reset: Callable[..., Any]  # (d, d0, mask) -> d
    read: Callable[..., Any]  # (qpos, qvel, qfrc_actuator, sensordata) -> (nworld, ncolumn + nsensordata)


_PROGRAMS: OrderedDict[tuple[Any, ...], _Programs] = OrderedDict()


def _programs(
    mx: mjx.Model,
    spec: RobotSpec,
    columns: list[StateColumn],
    nworld: int,
    device: jax.Device,
    deterministic: bool,
    held: tuple[int, int] | None = None,
    varied: tuple[str, ...] = (),
) -> _Programs:
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

    programs = _Programs(
        period=run,
        reset=jax.jit(reset, donate_argnums=0, compiler_options=options),
        read=jax.jit(read, compiler_options=options),
    )
    _PROGRAMS[key] = programs
    while len(_PROGRAMS) > _CACHE_SIZE:
        _PROGRAMS.popitem(last=False)
    return programs


def _holding(step: Callable[..., Any], held: Any, qpos: jax.Array, target: jax.Array) -> Callable[..., Any]:
    """A substep that first writes the held base velocity into qvel (batchsim.base_velocity's
    world_velocity, inlined): `target` (nworld, 3) body-frame vx, vy, wz, rotated by the base's
    orientation in `qpos` (the period's start); NaN rows leave the physics alone."""
    qposadr, dofadr = held
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


class MjxSystem(MjxFields, MjxDeviceIO, DeviceSystem):
    """`nworld` worlds on MJX (JAX), one jitted device loop per control period.

    Options:
      device: a JAX device, or "cpu", "gpu", "gpu:1", "tpu"; None is JAX's default (the
        first accelerator if there is one).
      deterministic: bitwise-repeatable results on a GPU (XLA's deterministic ops), slower.
    """

    name: ClassVar[str] = "mjx"
    OPTIONS: ClassVar[dict[str, Any]] = {"device": None, "deterministic": False}
    OPTION_TYPES: ClassVar[dict[str, type]] = {"device": object}  # _resolve_device takes a name or a jax.Device
    physics_memory = staticmethod(footprint.mjx)
    reads_torque_sensors: ClassVar[bool] = False  # its cfrc_int leaves out what C MuJoCo's torque sensors read

    @staticmethod
    def _resolve_device(option: Any) -> jax.Device:
        if option is None:
            return jax.devices()[0]
        if isinstance(option, jax.Device):
            return option
        platform, _, index = str(option).partition(":")
        platform = {"cuda": "gpu"}.get(platform, platform)
        return jax.devices(platform)[int(index or 0)]

    @staticmethod
    def _put_model(m: mujoco.MjModel, device: jax.Device) -> mjx.Model:
        return mjx.put_model(m, device=device, impl="jax")

    @staticmethod
    def available_devices() -> list[str]:
        """JAX's devices of its default platform, as this backend's `device` option names
        them ("gpu:0", "gpu:1", ...; "cpu:0", ... on a machine without an accelerator)."""
        devices = jax.devices()
        return [f"{d.platform}:{i}" for i, d in enumerate(devices)]

    # --- engine hooks ---
    def _open(self) -> None:
        m = self.model
        self._d0 = mjx.put_data(m, self._initial_data(), device=self.device, impl="jax")
        self._programs = _programs(
            self._model_on_device,
            self.spec,
            self._columns,
            self.nworld,
            self.device,
            bool(self.options["deterministic"]),
            None if self.base_velocity is None else (self.base_velocity.qposadr, self.base_velocity.dofadr),
            tuple(self._bound.fields) if self._bound is not None else (),
        )
        self._fields: dict[str, jax.Array] = {}  # the varied model fields, (nworld, *shape) each
        self._d = jax.tree.map(lambda x: jnp.repeat(x[None], self.nworld, axis=0), self._d0)
        self._ctrl = np.zeros((self.nworld, m.nu))
        self._ctrl_behind = False  # whether write_device() changed ctrl on the device since the host's was set
        self._ctrl32 = np.zeros((self.nworld, m.nu), np.float32)
        self._ctrl_on_device = True  # whether self._d.ctrl holds self._ctrl32
        self._clock = np.full(self.nworld, self.spec.initial.time)  # float64: the worlds' time
        self._packed: np.ndarray | None = None  # what the last period downloaded, while current
        # the base velocity's target (batchsim.base_velocity), NaN until write() stages one
        self._held32 = None if self.base_velocity is None else np.full((self.nworld, 3), np.nan, np.float32)
        self._held_on_device, self._held_dev = False, None
        self._xfrc32: np.ndarray | None = None  # external wrenches' xfrc_applied, from the first one on
        self._xfrc_on_device = True

    def _close(self) -> None:
        del self._d, self._d0, self._programs, self._fields

    def _ctrl_host(self) -> np.ndarray:
        if self._ctrl_behind:  # a reset or a write() after write_device(): start from the device's ctrl
            self._ctrl[:] = np.asarray(self._d.ctrl)
            self._ctrl_behind = False
        return self._ctrl

    def _upload_ctrl(self) -> None:
        # host side only: it goes up with the next step(), once however often write() ran
        np.copyto(self._ctrl32, self._ctrl, casting="same_kind")
        frozen = self.frozen
        if frozen.any():
            self._ctrl32[frozen] = 0.0  # parked worlds stay still
        self._ctrl_on_device = False

    def _sync_inputs(self) -> None:
        """ctrl, the base velocity's target and xfrc_applied (if write() changed them) and the
        float32 image of the float64 clock, up in one call."""
        inputs = {"time": self._clock.astype(np.float32)}
        if not self._ctrl_on_device:
            inputs["ctrl"] = self._ctrl32
        if not self._xfrc_on_device:
            inputs["xfrc_applied"] = self._xfrc32
        if self._held32 is not None and not self._held_on_device:
            inputs["held"] = self._held32
        inputs = jax.device_put(inputs, self.device)
        self._held_dev = inputs.pop("held", self._held_dev)
        self._d = self._d.replace(**inputs)
        self._ctrl_on_device = self._held_on_device = self._xfrc_on_device = True

    def _stage_base_velocity(self, target: np.ndarray) -> None:
        np.copyto(self._held32, target, casting="same_kind")  # up with the next step(), as ctrl
        self._held_on_device = False

    def _stage_xfrc(self, worlds: np.ndarray, xfrc: np.ndarray) -> None:
        if self._xfrc32 is None:
            self._xfrc32 = np.zeros((self.nworld, self.model.nbody, 6), np.float32)
        self._xfrc32[worlds] = xfrc  # the whole array up with the next step(), as ctrl
        self._xfrc_on_device = False

    def _read(self) -> None:
        packed = self._packed  # the last period's download, unless a reset has since changed the worlds
        if packed is None:
            d = self._d
            packed = np.asarray(self._programs.read(d.qpos, d.qvel, d.qfrc_actuator, d.sensordata))
        nread, nsensor = self._readings.shape[1], self._sensor_host.shape[1]
        np.copyto(self._readings, packed[:, :nread])
        np.copyto(self._sensor_host, packed[:, nread : nread + nsensor])
        np.copyto(self.time, self._clock)

    def _step(self, nstep: int) -> StepFailures | None:
        self._sync_inputs()
        held = () if self._held_dev is None else (self._held_dev,)
        self._d, out = self._programs.period(self._d, nstep, self._fields, *held)
        self._while_stepping()  # JAX dispatched the period; it runs on the device meanwhile
        out = np.asarray(out)  # one download: readings, then the failure codes
        self._packed, codes = out[:, :-1], out[:, -1]
        failures = None
        if codes.any():
            worlds = np.flatnonzero((codes != 0) & ~self.frozen)
            if worlds.size:
                # the program returned these worlds' readings from before the period
                nread = self._readings.shape[1]
                readings = self._packed[worlds, :nread].astype(np.float64)
                self._finish_gather(readings)  # an engine gather, unsigned like _read()'s
                failures = StepFailures(
                    worlds=worlds,
                    status=code_status(codes[worlds]),
                    reasons=self._failure_reasons(codes[worlds]),
                    readings=readings,
                    sensordata=self._packed[worlds, nread:].astype(np.float64),
                    time=self._clock[worlds].copy(),
                )
        dt = self.dt
        for _ in range(nstep):  # one addition per step, as mj_step adds them: cpu's time to the bit
            self._clock += dt
        return failures

    def _reset_on_device(self, worlds: np.ndarray | None) -> None:
        if worlds is None:
            mask = np.ones(self.nworld, bool)
        else:
            mask = np.zeros(self.nworld, bool)
            mask[worlds] = True
        self._d = self._programs.reset(self._d, self._d0, jax.device_put(mask, self.device))
        self._clock[mask] = self.spec.initial.time
        self._packed = None

    def _qstate(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        qpos, qvel = jax.device_get((self._d.qpos, self._d.qvel))
        return np.asarray(qpos)[worlds], np.asarray(qvel)[worlds]

    def _set_qstate(self, worlds: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        d = self._d
        self._d = d.replace(
            qpos=d.qpos.at[worlds].set(qpos.astype(d.qpos.dtype)), qvel=d.qvel.at[worlds].set(qvel.astype(d.qvel.dtype))
        )
        self._packed = None  # read() downloads the new state

    def _body_poses(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # both in one download, indexed on the host: a device-side gather compiles per world count
        xpos, xquat = jax.device_get((self._d.xpos, self._d.xquat))
        return np.asarray(xpos)[worlds], np.asarray(xquat)[worlds]

    # --- for users who stay on the device ---
    @property
    def data(self) -> mjx.Data:
        """The simulation's own `mjx.Data`, batched over worlds (every leaf `(nworld, ...)`).

        Valid until the next step(), write() or reset(), which donate its buffers. Assigning
        a Data of the same structure and shapes (one your own jitted program returned)
        replaces the simulation's state; read() then reads it, and a command write() made
        before goes in with the next step().
        """
        return self._d

    @data.setter
    def data(self, value: mjx.Data) -> None:
        self._d = value
        self._packed = None

    def device_arrays(self) -> dict[str, jax.Array]:
        """The simulation's JAX arrays, zero copy: qpos, qvel, qfrc_actuator, sensordata, ctrl
        `(nworld, ...)` and time `(nworld,)`, float32, on `self.device`.

        Each step() donates these buffers to the next period, so the arrays are valid until
        the next step(), write() or reset(): call device_arrays() again after those. Pass
        them on with DLPack (`torch.from_dlpack(a)`). Rows of frozen worlds (see `status`)
        are parked and meaningless until reset. `time` is the engine's float32 clock, set
        from `sim.time` (float64) at the start of each period.
        """
        self._sync_inputs()  # write() keeps ctrl on the host until the next step
        d = self._d
        return {f: getattr(d, f) for f in DEVICE_ARRAYS}

    # --- cameras and lidars: through a host copy of the worlds (MuJoCo's renderer, mujoco.batch rays) ---
    _host: HostSensors | None = None  # made on the first render or scan

    def _host_sensors(self) -> HostSensors:
        """The host mirror (its rows as last filled)."""
        if self._host is None:
            self._host = HostSensors(self.model, mjbatch.Batch(self.model, self.nworld, nthread=0))
        return self._host

    def _host_copy(self) -> HostSensors:
        """The host mirror, its state rows filled from the device: one download of qpos and mocap."""
        batch = self._host_sensors().batch
        fields = ["qpos"] + (["mocap_pos", "mocap_quat"] if self.model.nmocap else [])
        values = jax.device_get({f: getattr(self._d, f) for f in fields})
        for field, value in values.items():
            batch.bind(field)[:] = value
        return self._host

    def _render_frames(self, camera: Camera, worlds: np.ndarray, copy: bool) -> tuple[np.ndarray, np.ndarray]:
        return self._host_copy().frames(camera, worlds, copy)

    def _device_frames(self, camera: Camera) -> tuple[jax.Array, jax.Array]:
        """Every world's images, rendered on the host and put on this system's device."""
        rgb, depth = self._render_frames(camera, np.arange(self.nworld), False)
        return jax.device_put(rgb, self.device), jax.device_put(depth, self.device)

    def _prepare_rendering(self, cameras: list[Camera]) -> None:
        self._host_sensors().prepare(cameras)

    def _render_frames_later(self, camera: Camera, worlds: np.ndarray) -> Future:
        return self._host_copy().submit(camera, worlds)  # drawn on the render thread while the caller steps on

    def _cast_rays(self, lidar: Lidar, worlds: np.ndarray) -> np.ndarray:
        return self._host_copy().cast(lidar, worlds)

    def _device_ranges(self, lidar: Lidar) -> jax.Array:
        """Every world's ranges, cast on the host and put on this system's device."""
        return jax.device_put(self._ranges(lidar, np.arange(self.nworld)), self.device)

    def _close_sensors(self) -> None:
        if self._host is not None:
            self._host.close()
            self._host = None
