"""The `mjx` engine: MuJoCo XLA (`mujoco.mjx`, its JAX implementation) in float32.

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

from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import batch as mjbatch
from mujoco import mjx

from batchsim.backends import footprint
from batchsim.backends.device import DEVICE_ARRAYS, DeviceEngine, code_status
from batchsim.backends.host_sensors import HostSensors
from batchsim.backends.mjx.fields import scatter_rows, variable_fields
from batchsim.backends.mjx.programs import device_programs, programs
from batchsim.sensors import Camera, Lidar
from batchsim.types import HeldBase, StepFailures


class MjxEngine(DeviceEngine):
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

    @classmethod
    def variable_fields(cls, m: mujoco.MjModel) -> frozenset[str]:
        """The fields MJX's Model holds as arrays of the MjModel's shape (a vmapped model takes
        them per world); its options likewise, as `opt.<name>`."""
        return variable_fields(m)

    # --- the engine ---
    def open(self, *, held_base: HeldBase | None = None, varied: tuple[str, ...] = ()) -> None:
        m = self.model
        self._d0 = mjx.put_data(m, self._initial_data(), device=self.device, impl="jax")
        self._programs = programs(
            self._model_on_device,
            self.spec,
            self.buffers.columns,
            self.nworld,
            self.device,
            bool(self.options["deterministic"]),
            held_base,
            varied,
        )
        self._fields: dict[str, jax.Array] = {}  # the varied model fields, (nworld, *shape) each
        self._d = jax.tree.map(lambda x: jnp.repeat(x[None], self.nworld, axis=0), self._d0)
        self._ctrl = np.zeros((self.nworld, m.nu))
        self._ctrl_behind = False  # whether write_device() changed ctrl on the device since the host's was set
        self._ctrl32 = np.zeros((self.nworld, m.nu), np.float32)
        self._ctrl_on_device = True  # whether self._d.ctrl holds self._ctrl32
        self._clock = np.full(self.nworld, self.spec.initial.time)  # float64: the worlds' time
        self._packed: np.ndarray | None = None  # what the last period downloaded, while current
        # the base velocity's target (batchsim.plugins.base_velocity), NaN until write() stages one
        self._held32 = None if held_base is None else np.full((self.nworld, 3), np.nan, np.float32)
        self._held_on_device, self._held_dev = False, None
        self._xfrc32: np.ndarray | None = None  # external wrenches' xfrc_applied, from the first one on
        self._xfrc_on_device = True
        self._device_programs: tuple[Any, Any] | None = None  # device_state's and write_device's

    def close(self) -> None:
        del self._d, self._d0, self._programs, self._fields

    def ctrl(self) -> np.ndarray:
        if self._ctrl_behind:  # a reset or a write() after write_device(): start from the device's ctrl
            self._ctrl[:] = np.asarray(self._d.ctrl)
            self._ctrl_behind = False
        return self._ctrl

    def upload_ctrl(self) -> None:
        # host side only: it goes up with the next step(), once however often write() ran
        np.copyto(self._ctrl32, self._ctrl, casting="same_kind")
        frozen = self.buffers.frozen
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

    def stage_base_velocity(self, target: np.ndarray) -> None:
        np.copyto(self._held32, target, casting="same_kind")  # up with the next step(), as ctrl
        self._held_on_device = False

    def stage_xfrc(self, worlds: np.ndarray, xfrc: np.ndarray) -> None:
        if self._xfrc32 is None:
            self._xfrc32 = np.zeros((self.nworld, self.model.nbody, 6), np.float32)
        self._xfrc32[worlds] = xfrc  # the whole array up with the next step(), as ctrl
        self._xfrc_on_device = False

    def read(self) -> None:
        packed = self._packed  # the last period's download, unless a reset has since changed the worlds
        if packed is None:
            d = self._d
            packed = np.asarray(self._programs.read(d.qpos, d.qvel, d.qfrc_actuator, d.sensordata))
        b = self.buffers
        nread, nsensor = b.readings.shape[1], b.sensordata.shape[1]
        np.copyto(b.readings, packed[:, :nread])
        np.copyto(b.sensordata, packed[:, nread : nread + nsensor])
        np.copyto(b.time, self._clock)

    def step(
        self, nstep: int, meanwhile: Callable[[], None], start: tuple[np.ndarray, ...] | None
    ) -> StepFailures | None:
        self._sync_inputs()
        held = () if self._held_dev is None else (self._held_dev,)
        self._d, out = self._programs.period(self._d, nstep, self._fields, *held)
        meanwhile()  # JAX dispatched the period; it runs on the device meanwhile
        out = np.asarray(out)  # one download: readings, then the failure codes
        self._packed, codes = out[:, :-1], out[:, -1]
        failures = None
        if codes.any():
            worlds = np.flatnonzero((codes != 0) & ~self.buffers.frozen)
            if worlds.size:
                # the program returned these worlds' readings from before the period (raw: the contract finishes them)
                nread = self.buffers.readings.shape[1]
                readings = self._packed[worlds, :nread].astype(np.float64)
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

    def qstate(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        qpos, qvel = jax.device_get((self._d.qpos, self._d.qvel))
        return np.asarray(qpos)[worlds], np.asarray(qvel)[worlds]

    def set_qstate(self, worlds: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        d = self._d
        self._d = d.replace(
            qpos=d.qpos.at[worlds].set(qpos.astype(d.qpos.dtype)), qvel=d.qvel.at[worlds].set(qvel.astype(d.qvel.dtype))
        )
        self._packed = None  # read() downloads the new state

    def body_poses(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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

    def render_frames(self, camera: Camera, worlds: np.ndarray, copy: bool) -> tuple[np.ndarray, np.ndarray]:
        return self._host_copy().frames(camera, worlds, copy)

    def device_frames(self, camera: Camera) -> tuple[jax.Array, jax.Array]:
        """Every world's images, rendered on the host and put on this engine's device."""
        rgb, depth = self.render_frames(camera, np.arange(self.nworld), False)
        return self.to_device(rgb), self.to_device(depth)

    def prepare_rendering(self, cameras: list[Camera]) -> None:
        self._host_sensors().prepare(cameras)

    def render_frames_later(self, camera: Camera, worlds: np.ndarray) -> Future:
        return self._host_copy().submit(camera, worlds)  # drawn on the render thread while the caller steps on

    def cast_rays(self, lidar: Lidar, worlds: np.ndarray) -> np.ndarray:
        return self._host_copy().cast(lidar, worlds)

    def to_device(self, array: np.ndarray) -> jax.Array:
        """A host array (a render's, a scan's) put on this engine's device."""
        return jax.device_put(array, self.device)

    def close_sensors(self) -> None:
        if self._host is not None:
            self._host.close()
            self._host = None

    # --- the device path: the state gathered and signed, commands into ctrl, by jitted programs ---
    def _device_jits(self) -> tuple[Any, Any]:
        if self._device_programs is None:
            sign = np.array([c.sign for c in self.spec.state], np.float32)
            self._device_programs = device_programs(self._programs, self.spec, sign)
        return self._device_programs

    def device_state(self, sign: np.ndarray) -> jax.Array:
        d = self._d
        return self._device_jits()[0](d.qpos, d.qvel, d.qfrc_actuator, d.sensordata)

    def write_device(self, command: Any) -> None:
        self._sync_inputs()  # what write() staged on the host goes up first, then the device's command over it
        source = command if isinstance(command, jax.Array) else jax.dlpack.from_dlpack(command)
        if source.dtype not in (jnp.float32, jnp.float64):
            raise ValueError(f"command must be float32 or float64, got {source.dtype}")
        parked = jax.device_put(self.buffers.frozen, self.device)
        self._d = self._d.replace(ctrl=self._device_jits()[1](self._d.ctrl, source, parked))
        self._ctrl_behind = True  # the host's ctrl, which resets upload whole, is brought down when wanted
        self._packed = None

    # --- per-world model fields (batchsim.backends.mjx.fields) ---
    def set_model_fields(self, worlds: np.ndarray, params: dict[str, np.ndarray]) -> None:
        if not self._fields or len(worlds) == self.nworld:  # the first draw: every world's, up
            self._fields = jax.device_put({f: v.astype(np.float32) for f, v in params.items()}, self.device)
        else:  # a redraw: those worlds' rows up, scattered on the device
            rows = {f: v[worlds].astype(np.float32) for f, v in params.items()}
            self._fields = scatter_rows(self._fields, jax.device_put(worlds.astype(np.int32), self.device), rows)
        self._packed = None
