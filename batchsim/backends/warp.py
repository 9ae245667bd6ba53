"""The `warp` backend: MuJoCo Warp (`mujoco_warp`) in float32, on an NVIDIA GPU or Warp's CPU device.

One control period is one CUDA graph: the `nstep` physics steps and a per-world check
kernel, captured once per `nstep` and launched with one call. Commands go up and state
comes down once per period (`write`, `read`), through pinned host buffers allocated once
at configure; nothing crosses the bus per physics step. On Warp's CPU device (a machine
without a GPU) the same kernels run as plain launches.

Failures are data, as in MuJoCo Warp itself: a world whose qpos, qvel or qacc goes
non-finite or beyond MuJoCo's mjMAXVAL gets DIVERGED, a world whose contact or constraint
buffers overflow gets OVERFLOW. Such a world is frozen: its state and time read as they
were when it failed, while on the device it is parked (reset, ctrl held at zero) so that
it costs the others nothing, until `reset()` lists it.

Contact and constraint buffers (`nconmax` per world on average, pooled over the worlds as
MuJoCo Warp does, and `njmax` per world) are sized from a short CPU rollout of the model,
with headroom; both are options of `batchsim.make`. A contact-pool overflow cannot be
pinned to one world, so it sets OVERFLOW on every world; a constraint overflow is per
world. Each kind is reported once, in one line naming the option that fixes it.

`device_arrays()` hands out the live Warp arrays (zero copy, DLPack-capable) for users
who stay on the device.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from typing import Any, ClassVar

import mujoco
import numpy as np
import warp as wp

wp.config.quiet = True  # no banner on stdout: `batchsim info` and the CLI print there
if wp.config.log_level <= wp.LOG_INFO:
    wp.config.log_level = wp.LOG_WARNING  # no "Module ... load on device" line per kernel

import mujoco_warp as mjw  # noqa: E402  (after the config above)
from mujoco_warp._src import types as _warp_types  # noqa: E402  (vec6, the geom-group mask rays() takes)

from batchsim.backends import unsupported_error  # noqa: E402
from batchsim.hardware import MAX_COMMAND, BatchedSystem, Status  # noqa: E402
from batchsim.model import RobotSpec  # noqa: E402
from batchsim.sensors import Camera, Lidar  # noqa: E402

log = logging.getLogger("batchsim.warp")

_O = mjw.OverflowType
# Buffers that, once full, drop contacts or constraints: the world's results are wrong.
# ITERATIONS / LS_ITERATIONS only say the solver stopped early, as MuJoCo's does.
_BUFFER_OVERFLOWS = int(
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
# what to tell the user for each kind: (what filled up, the option that fixes it)
_OVERFLOW_FIX = {
    _O.NEFC: ("constraint rows (njmax)", "njmax"),
    _O.NJMAX_NNZ: ("constraint Jacobian non-zeros (njmax)", "njmax"),
    _O.BROADPHASE: ("contact candidates (nconmax, pooled over worlds)", "nconmax"),
    _O.NARROWPHASE: ("contacts (nconmax, pooled over worlds)", "nconmax"),
    _O.CCD: ("convex-collision contacts (nconmax)", "nconmax"),
    _O.HFIELD: ("height-field contacts (nconmax)", "nconmax"),
    _O.CONTACT_MATCH: ("contact-sensor matches", "nconmax"),
    _O.NVMAX: ("island degrees of freedom", "njmax"),
    _O.EPA_HORIZON: ("the convex-collision EPA horizon", "nconmax"),
    _O.TACTILE: ("tactile-sensor pairs", "nconmax"),
}
_SOURCES = ("qpos", "qvel", "qfrc_actuator", "sensordata")

# buffer sizing from a CPU rollout
_SIZING_SECONDS = 2.0
_SIZING_MAX_STEPS = 2000
_HEADROOM = 2.0


# ---------------------------------------------------------------- kernels


@wp.kernel
def _check_worlds(
    qpos: wp.array2d(dtype=wp.float32),
    qvel: wp.array2d(dtype=wp.float32),
    qacc: wp.array2d(dtype=wp.float32),
    overflow: wp.array(dtype=wp.int32),
    overflow_mask: wp.int32,
    maxval: wp.float32,
    flags: wp.array(dtype=wp.int32),
):
    """flags[w]: DIVERGED if qpos/qvel/qacc is NaN or beyond mjMAXVAL, OVERFLOW if a buffer overflowed."""
    w = wp.tid()
    bad = int(0)  # noqa: UP018  (int(): a mutable Warp variable, not a constant)
    for i in range(qpos.shape[1]):
        x = qpos[w, i]
        if wp.isnan(x) or wp.abs(x) > maxval:
            bad = 1
    for i in range(qvel.shape[1]):
        x = qvel[w, i]
        y = qacc[w, i]
        if wp.isnan(x) or wp.abs(x) > maxval or wp.isnan(y) or wp.abs(y) > maxval:
            bad = 1
    f = int(0)  # noqa: UP018
    if bad != 0:
        f = int(Status.DIVERGED)
    if (overflow[w] & overflow_mask) != 0:
        f = f | int(Status.OVERFLOW)
    flags[w] = f


@wp.kernel
def _narrow_ctrl(
    ctrl64: wp.array2d(dtype=wp.float64),
    parked: wp.array(dtype=wp.int32),
    ctrl: wp.array2d(dtype=wp.float32),
):
    """The host's float64 ctrl into the simulation's float32 ctrl; parked worlds get zero."""
    w, j = wp.tid()
    if parked[w] != 0:
        ctrl[w, j] = wp.float32(0.0)
    else:
        ctrl[w, j] = wp.float32(ctrl64[w, j])


@wp.kernel
def _gather_state(
    qpos: wp.array2d(dtype=wp.float32),
    qvel: wp.array2d(dtype=wp.float32),
    qfrc_actuator: wp.array2d(dtype=wp.float32),
    sensordata: wp.array2d(dtype=wp.float32),
    time: wp.array(dtype=wp.float32),
    source: wp.array(dtype=wp.int32),
    index: wp.array(dtype=wp.int32),
    nstate: wp.int32,
    state_out: wp.array2d(dtype=wp.float64),
    sensordata_out: wp.array2d(dtype=wp.float64),
    time_out: wp.array(dtype=wp.float64),
):
    """The state interfaces, sensordata and time of every world, widened to float64.

    Column c < nstate is state column c, read from field source[c] at index[c]; the next
    nsensordata columns are sensordata; the last is time.
    """
    w, c = wp.tid()
    if c < nstate:
        s = source[c]
        i = index[c]
        v = wp.float32(0.0)
        if s == 0:
            v = qpos[w, i]
        elif s == 1:
            v = qvel[w, i]
        elif s == 2:
            v = qfrc_actuator[w, i]
        else:
            v = sensordata[w, i]
        state_out[w, c] = wp.float64(v)
    elif c < nstate + sensordata.shape[1]:
        sensordata_out[w, c - nstate] = wp.float64(sensordata[w, c - nstate])
    else:
        time_out[w] = wp.float64(time[w])


@wp.kernel
def _set_rows(mask: wp.array(dtype=wp.bool), row: wp.array(dtype=Any), out: wp.array2d(dtype=Any)):
    """out[w] = row for the masked worlds (float32, vec3 or quat rows)."""
    w, j = wp.tid()
    if mask[w]:
        out[w, j] = row[j]


@wp.kernel
def _set_time(mask: wp.array(dtype=wp.bool), value: wp.float32, out: wp.array(dtype=wp.float32)):
    w = wp.tid()
    if mask[w]:
        out[w] = value


# ---------------------------------------------------------------- buffer sizing


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


# ---------------------------------------------------------------- the backend


class WarpSystem(BatchedSystem):
    """`nworld` worlds on MuJoCo Warp, one CUDA graph per control period.

    Options:
      nconmax: contacts per world, on average (MuJoCo Warp pools them over the worlds);
        None sizes it from a short CPU rollout of the model, with headroom.
      njmax: constraint rows per world; None sizes it from the same rollout.
      device: a Warp device ("cuda:0", "cpu"); None is Warp's default (the first GPU if
        there is one).
      graph: capture each control period in a CUDA graph (GPU only); False launches the
        kernels one by one, for debugging.
      deterministic: bitwise-repeatable results on a GPU (MuJoCo Warp's sorted contacts,
        canonical constraint rows and order-invariant atomic sums), slower. Warp's CPU
        device is repeatable either way.
    """

    name: ClassVar[str] = "warp"
    OPTIONS: ClassVar[dict[str, Any]] = {
        "nconmax": None,
        "njmax": None,
        "device": None,
        "graph": True,
        "deterministic": False,
    }

    def __init__(self, spec: RobotSpec, nworld: int, **options: Any):
        super().__init__(spec, nworld, **options)
        self.device = wp.get_device(self.options["device"])
        feature = self.unsupported(spec, self.device)
        if feature is not None:
            raise unsupported_error("warp", spec, feature)
        sized = None
        if self.options["nconmax"] is None or self.options["njmax"] is None:
            sized = rollout_sizes(self.model)
        self.nconmax = int(self.options["nconmax"] if self.options["nconmax"] is not None else sized[0])
        self.njmax = int(self.options["njmax"] if self.options["njmax"] is not None else sized[1])
        self._cuda = self.device.is_cuda
        # The host arrays a user sees become pinned memory that the device copies into
        # directly: read() then costs one DMA per array and no host-side copy or conversion.
        self._state_wp = self._host_array(self._readings.shape, wp.float64)
        self._sensor_wp = self._host_array(self._sensor_host.shape, wp.float64)
        self._time_wp = self._host_array(self.time.shape, wp.float64)
        self._ctrl_wp = self._host_array((self.nworld, self.model.nu), wp.float64)
        self._flags_wp = self._host_array((self.nworld,), wp.int32)
        self._bind_readings(self._state_wp.numpy())
        self._sensor_host = self._sensor_wp.numpy()
        self.sensordata = type(self.sensordata)(
            {s.name: self._sensor_host[:, s.adr : s.adr + s.dim] for s in spec.sensors}
        )
        self.time = self._time_wp.numpy()
        self._ctrl = self._ctrl_wp.numpy()
        self._flags = self._flags_wp.numpy()
        self._reported: set[int] = set()

    @staticmethod
    def available_devices() -> list[str]:
        """Warp's devices for this backend: every CUDA GPU ("cuda:0", ...), else ["cpu"]."""
        gpus = [d.alias for d in wp.get_cuda_devices()]
        return gpus or ["cpu"]

    @staticmethod
    def unsupported(spec: RobotSpec, device: Any = None) -> str | None:
        """The model feature MuJoCo Warp cannot simulate, or None."""
        try:
            with wp.ScopedDevice(device):
                mjw.put_model(spec.mjmodel)
        except NotImplementedError as e:
            return str(e).strip().rstrip(".") or type(e).__name__
        return None

    def _host_array(self, shape: tuple[int, ...], dtype: Any) -> wp.array:
        """A zeroed host array: pinned (page-locked) when the device is a GPU."""
        return wp.zeros(shape, dtype=dtype, device="cpu", pinned=self._cuda)

    # --- engine hooks ---
    def _open(self) -> None:
        m, n = self.model, self.nworld
        mjd = mujoco.MjData(m)
        self.spec.initial.apply(m, mjd)  # with mj_forward: a reset world reads what cpu's reads
        with wp.ScopedDevice(self.device):
            self._m = mjw.put_model(m)
            # failures are read per world from d.overflow; MuJoCo Warp's own printf per
            # overflowing world and step would flood the console
            self._m.opt.warn_overflow = 0
            if self.options["deterministic"]:
                self._m.opt.deterministic = int(mjw.DeterminismType.ALL)
            self._d = mjw.put_data(m, mjd, nworld=n, nconmax=self.nconmax, njmax=self.njmax)
            d = self._d
            # what a reset world is set to beyond reset_data's defaults: the initial state (a
            # keyframe, initial values) and mj_forward's derived fields of it
            self._initial_rows = {
                field: wp.array(np.asarray(getattr(mjd, field), np.float32), dtype=dtype)
                for field, dtype in (
                    ("qpos", wp.float32),
                    ("qvel", wp.float32),
                    ("act", wp.float32),
                    ("ctrl", wp.float32),
                    ("qfrc_actuator", wp.float32),
                    ("sensordata", wp.float32),
                    ("mocap_pos", wp.vec3),
                    ("mocap_quat", wp.quat),
                )
                if getattr(mjd, field).size
            }
            self._time0 = float(mjd.time)
            self._parked_dev = wp.zeros(n, dtype=wp.int32)
            self._mask_dev = wp.zeros(n, dtype=wp.bool)
            nread = self._readings.shape[1]
            source = np.zeros(nread, np.int32)
            index = np.zeros(nread, np.int32)
            for c, col in enumerate(self._columns):
                source[c], index[c] = _SOURCES.index(col.source), col.index
            self._source = wp.array(source, dtype=wp.int32)
            self._index = wp.array(index, dtype=wp.int32)
            if self._cuda:
                self._state_dev = wp.zeros(self._readings.shape, dtype=wp.float64)
                self._sensor_dev = wp.zeros(self._sensor_host.shape, dtype=wp.float64)
                self._time_dev = wp.zeros(n, dtype=wp.float64)
                self._ctrl_dev = wp.zeros(self._ctrl.shape, dtype=wp.float64)
                self._flags_dev = wp.zeros(n, dtype=wp.int32)
            else:  # Warp's CPU device: the kernels read and write the host arrays themselves
                self._state_dev, self._sensor_dev, self._time_dev = (
                    self._state_wp,
                    self._sensor_wp,
                    self._time_wp,
                )
                self._ctrl_dev, self._flags_dev = self._ctrl_wp, self._flags_wp
        del d
        self._graphs: dict[int, Any] = {}
        self._init_parking()
        self._ncols = self._readings.shape[1] + self._sensor_host.shape[1] + 1

    def _close(self) -> None:
        self._graphs.clear()
        for name in ("_m", "_d", "_initial_rows", "_parked_dev", "_mask_dev", "_source", "_index"):
            self.__dict__.pop(name, None)

    def _ctrl_host(self) -> np.ndarray:
        return self._ctrl

    def _upload_ctrl(self) -> None:
        with wp.ScopedDevice(self.device):
            if self._cuda:
                wp.copy(self._ctrl_dev, self._ctrl_wp)
            wp.launch(
                _narrow_ctrl,
                dim=self._ctrl.shape,
                inputs=[self._ctrl_dev, self._parked_dev],
                outputs=[self._d.ctrl],
            )

    def _download(self) -> Mapping[str, np.ndarray]:
        """Host float64 copies of the raw fields; read() itself takes the faster path of _refresh."""
        return {f: getattr(self._d, f).numpy().astype(np.float64) for f in (*_SOURCES, "time")}

    def _refresh(self) -> None:
        d = self._d
        with wp.ScopedDevice(self.device):
            wp.launch(
                _gather_state,
                dim=(self.nworld, self._ncols),
                inputs=[
                    d.qpos,
                    d.qvel,
                    d.qfrc_actuator,
                    d.sensordata,
                    d.time,
                    self._source,
                    self._index,
                    self._readings.shape[1],
                ],
                outputs=[self._state_dev, self._sensor_dev, self._time_dev],
            )
            if self._cuda:
                wp.copy(self._state_wp, self._state_dev)
                if self._sensor_host.size:
                    wp.copy(self._sensor_wp, self._sensor_dev)
                wp.copy(self._time_wp, self._time_dev)
            wp.synchronize_device(self.device)
        self._apply_signs()
        self._show_held_readings()

    def _step(self, nstep: int) -> None:
        with wp.ScopedDevice(self.device):
            if self._cuda and self.options["graph"]:
                graph = self._graphs.get(nstep)
                if graph is None:
                    graph = self._graphs[nstep] = self._capture(nstep)
                wp.capture_launch(graph)
            else:
                self._period(nstep)
            if self._cuda:
                wp.copy(self._flags_wp, self._flags_dev)
            wp.synchronize_device(self.device)
        flags = self._flags
        if flags.any():
            failed = (flags != 0) & ~self._parked
            if failed.any():
                self._freeze(np.flatnonzero(failed), flags)

    def _period(self, nstep: int) -> None:
        m, d = self._m, self._d
        for _ in range(nstep):
            mjw.step(m, d)
        wp.launch(
            _check_worlds,
            dim=self.nworld,
            inputs=[d.qpos, d.qvel, d.qacc, d.overflow, _BUFFER_OVERFLOWS, float(MAX_COMMAND)],
            outputs=[self._flags_dev],
        )

    def _capture(self, nstep: int) -> Any:
        with wp.ScopedCapture(device=self.device) as capture:
            self._period(nstep)
        return capture.graph

    def _freeze(self, worlds: np.ndarray, flags: np.ndarray) -> None:
        """Hold what the failed worlds read now, then park them on the device."""
        self.status[worlds] |= flags[worlds].astype(np.uint8)
        overflowed = worlds[(flags[worlds] & int(Status.OVERFLOW)) != 0]
        if overflowed.size:
            self._report_overflow(overflowed)
        self._refresh()  # the newly failed worlds are not parked yet: they read live, once
        self._hold_readings(worlds)
        self._reset_on_device(worlds)
        with wp.ScopedDevice(self.device):
            self._parked_dev.assign(self._parked.astype(np.int32))
        self._upload_ctrl()

    def _report_overflow(self, worlds: np.ndarray) -> None:
        overflow = self._d.overflow.numpy()[worlds] & _BUFFER_OVERFLOWS
        for kind, (what, option) in _OVERFLOW_FIX.items():
            hit = (overflow & int(kind)) != 0
            if not hit.any() or int(kind) in self._reported:
                continue
            self._reported.add(int(kind))
            now = self.nconmax if option == "nconmax" else self.njmax
            log.warning(
                "batchsim: warp: %s overflowed in %d of %d worlds; they are frozen with OVERFLOW until "
                "reset. Fix: batchsim.make(..., %s=%d) (now %d)",
                what,
                int(hit.sum()),
                self.nworld,
                option,
                2 * now,
                now,
            )

    def _reset_on_device(self, worlds: np.ndarray | None) -> None:
        mask = np.ones(self.nworld, bool) if worlds is None else np.isin(np.arange(self.nworld), worlds)
        with wp.ScopedDevice(self.device):
            self._mask_dev.assign(mask)
            mjw.reset_data(self._m, self._d, reset=self._mask_dev)
            d = self._d
            # the initial state, and mj_forward's qfrc_actuator and sensordata of it, as on cpu
            for field, row in self._initial_rows.items():
                wp.launch(
                    _set_rows,
                    dim=(self.nworld, row.shape[0]),
                    inputs=[self._mask_dev, row],
                    outputs=[getattr(d, field)],
                )
            if self._time0:
                wp.launch(_set_time, dim=self.nworld, inputs=[self._mask_dev, self._time0], outputs=[d.time])

    def _reset(self, worlds: np.ndarray | None) -> None:
        self._reset_on_device(worlds)
        self._unpark(worlds)
        with wp.ScopedDevice(self.device):
            self._parked_dev.assign(self._parked.astype(np.int32))

    # --- for users who stay on the device ---
    def device_arrays(self) -> dict[str, wp.array]:
        """The simulation's live Warp arrays, zero copy: qpos, qvel, qfrc_actuator, sensordata,
        ctrl `(nworld, ...)` and time `(nworld,)`, float32, on `self.device`.

        They are the buffers MuJoCo Warp steps in place, valid until cleanup(); pass them to
        other frameworks with DLPack (`torch.from_dlpack(a)`, `jax.dlpack.from_dlpack(a)`).
        Rows of frozen worlds (see `status`) are parked and meaningless until reset.
        """
        d = self._d
        return {f: getattr(d, f) for f in ("qpos", "qvel", "qfrc_actuator", "sensordata", "ctrl", "time")}

    # --- cameras and lidars: MuJoCo Warp's ray-traced rendering and ray casting ---
    sensors_batched: ClassVar[bool] = True  # every world in one launch, whichever are asked for
    _render_contexts: dict[str, Any] | None = None  # per camera: (render context, rgb, depth, host rgb, host depth)
    _lidar_buffers: dict[str, Any] | None = None  # per lidar: its rays and results, on the device and host

    def _sensor_kinematics(self, cameras: bool) -> None:
        """Positions of bodies, geoms and sites (and cameras, lights) from the current qpos.

        After a step they describe the state before its last substep, and after a reset they
        are stale; images and scans show the current state, as on cpu.
        """
        m, d = self._m, self._d
        mjw.kinematics(m, d)
        if cameras:
            modes = (int(mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM), int(mujoco.mjtCamLight.mjCAMLIGHT_TARGETBODYCOM))
            if np.isin(self.model.cam_mode, modes).any() or np.isin(self.model.light_mode, modes).any():
                mjw.com_pos(m, d)
            mjw.camlight(m, d)

    def _device_frames(self, camera: Camera) -> tuple[wp.array, wp.array]:
        """Every world's images of `camera` on the device: (nworld, H, W, 3) uint8 and (nworld, H, W)
        float32 Warp arrays, overwritten by the next render of this camera."""
        if self._render_contexts is None:
            self._render_contexts = {}
        entry = self._render_contexts.get(camera.name)
        with wp.ScopedDevice(self.device):
            if entry is None:
                rc = mjw.create_render_context(
                    self.model,
                    nworld=self.nworld,
                    cam_res=[(camera.width, camera.height)],
                    render_rgb=True,
                    render_depth=True,
                    cam_active=[camera.id],
                )
                shape = (self.nworld, camera.height, camera.width)
                entry = self._render_contexts[camera.name] = (
                    rc,
                    wp.zeros((*shape, 3), dtype=wp.uint8),
                    wp.zeros(shape, dtype=wp.float32),
                    self._host_array((*shape, 3), wp.uint8),
                    self._host_array(shape, wp.float32),
                )
            rc, rgb, depth = entry[:3]
            self._sensor_kinematics(cameras=True)
            mjw.refit_bvh(self._m, self._d, rc)
            mjw.render(self._m, self._d, rc)
            wp.launch(_unpack_frames, dim=depth.shape, inputs=[rc.rgb_data, rc.depth_data], outputs=[rgb, depth])
        return rgb, depth

    def _render_frames(self, camera: Camera, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rgb, depth = self._device_frames(camera)
        host_rgb, host_depth = self._render_contexts[camera.name][3:]
        with wp.ScopedDevice(self.device):
            if self._cuda:
                wp.copy(host_rgb, rgb)
                wp.copy(host_depth, depth)
            else:
                host_rgb, host_depth = rgb, depth
            wp.synchronize_device(self.device)
        rgb_np, depth_np = host_rgb.numpy(), host_depth.numpy()
        if len(worlds) == self.nworld:  # every world: the buffers themselves (render() copies unless told not to)
            return rgb_np, depth_np
        return rgb_np[worlds], depth_np[worlds]

    def _cast_rays(self, lidar: Lidar, worlds: np.ndarray) -> np.ndarray:
        if self._lidar_buffers is None:
            self._lidar_buffers = {}
        buffers = self._lidar_buffers.get(lidar.name)
        shape = (self.nworld, lidar.nray)
        with wp.ScopedDevice(self.device):
            if buffers is None:
                buffers = self._lidar_buffers[lidar.name] = {
                    "directions": wp.array(lidar.directions.astype(np.float32), dtype=wp.vec3),
                    "exclude": wp.full(lidar.nray, lidar.body_id, dtype=wp.int32),
                    "pnt": wp.zeros(shape, dtype=wp.vec3),
                    "vec": wp.zeros(shape, dtype=wp.vec3),
                    "dist": wp.zeros(shape, dtype=wp.float32),
                    "geomid": wp.zeros(shape, dtype=wp.int32),
                    "normal": wp.zeros(shape, dtype=wp.vec3),
                    "host": self._host_array(shape, wp.float32),
                }
            b = buffers
            self._sensor_kinematics(cameras=False)
            wp.launch(
                _lidar_rays,
                dim=shape,
                inputs=[self._d.site_xpos, self._d.site_xmat, lidar.site_id, b["directions"]],
                outputs=[b["pnt"], b["vec"]],
            )
            everything = _warp_types.vec6(-1.0, -1.0, -1.0, -1.0, -1.0, -1.0)  # every geom group
            mjw.rays(self._m, self._d, b["pnt"], b["vec"], everything, True, b["exclude"], b["dist"], b["geomid"], b["normal"])
            host = b["host"]
            if self._cuda:
                wp.copy(host, b["dist"])
            else:
                host = b["dist"]
            wp.synchronize_device(self.device)
        dist = host.numpy()
        return dist if len(worlds) == self.nworld else dist[worlds]

    def _close_sensors(self) -> None:
        self._render_contexts = self._lidar_buffers = None


@wp.kernel
def _unpack_frames(
    rgb_packed: wp.array2d(dtype=wp.uint32),
    depth_in: wp.array2d(dtype=wp.float32),
    rgb_out: wp.array4d(dtype=wp.uint8),
    depth_out: wp.array3d(dtype=wp.float32),
):
    """MuJoCo Warp's packed 0xAARRGGBB pixels and depth (0: no hit) as (H, W, 3) uint8 and metres, +inf."""
    w, y, x = wp.tid()
    p = y * depth_out.shape[2] + x
    c = rgb_packed[w, p]
    rgb_out[w, y, x, 0] = wp.uint8((c >> wp.uint32(16)) & wp.uint32(0xFF))
    rgb_out[w, y, x, 1] = wp.uint8((c >> wp.uint32(8)) & wp.uint32(0xFF))
    rgb_out[w, y, x, 2] = wp.uint8(c & wp.uint32(0xFF))
    z = depth_in[w, p]
    if z > wp.float32(0.0):
        depth_out[w, y, x] = z
    else:
        depth_out[w, y, x] = wp.inf


@wp.kernel
def _lidar_rays(
    site_xpos: wp.array2d(dtype=wp.vec3),
    site_xmat: wp.array2d(dtype=wp.mat33),
    site: int,
    directions: wp.array(dtype=wp.vec3),
    pnt_out: wp.array2d(dtype=wp.vec3),
    vec_out: wp.array2d(dtype=wp.vec3),
):
    """World-frame origins and directions of a lidar's rays in every world."""
    w, r = wp.tid()
    pnt_out[w, r] = site_xpos[w, site]
    vec_out[w, r] = site_xmat[w, site] @ directions[r]
