"""The `warp` backend: MuJoCo Warp (`mujoco_warp`) in float32, on an NVIDIA GPU or Warp's CPU device.

One control period is one captured graph: the `nstep` physics steps, the float64 clock and
a per-world check kernel, captured once per `nstep` and launched with one call (Warp replays
graphs on its CPU device too). Commands go up and state comes down once per period
(`write`, `read`), through pinned host buffers allocated once at configure; nothing crosses
the bus per physics step.

Failures are data, as in MuJoCo Warp itself: a world whose qpos, qvel or qacc goes
non-finite or beyond MuJoCo's mjMAXVAL gets DIVERGED. Such a world is frozen: it reads as it
did before the step() in which it failed, while on the device it is parked (reset, ctrl
held at zero) so that it costs the others nothing, until `reset()` lists it.

Buffers grow instead of freezing the fleet. Contact and constraint buffers (`nconmax` per
world on average, pooled over the worlds as MuJoCo Warp does, and `njmax` per world) start
at the size a short CPU rollout of the model suggests, with headroom (or the options'). Each
period starts by keeping a device-side copy of every world's integration state; when a
period overflows one of them, the buffers are re-allocated larger (at least twice, more
where MuJoCo Warp's counters say so), the state carried over, the graphs re-captured and the
period run again from its start, so that its result is as if the buffers had been big
enough; one log line says what grew and to what. Only what cannot grow freezes worlds with
OVERFLOW: the device's free memory (or `max_data_bytes`), or a limit of the model itself
(height-field contacts per pair, tactile pairs, the EPA horizon).

Time is float64: a device-side float64 clock per world, advanced in the graph one addition
per step as mj_step adds them, copied into MuJoCo Warp's float32 `d.time` each period.

`device_arrays()` hands out the live Warp arrays (zero copy, DLPack-capable) for users
who stay on the device.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import threading
from typing import Any, ClassVar

import mujoco
import numpy as np
import warp as wp

wp.config.quiet = True  # no banner on stdout: `batchsim info` and the CLI print there
if wp.config.log_level <= wp.LOG_INFO:
    wp.config.log_level = wp.LOG_WARNING  # no "Module ... load on device" line per kernel

import mujoco_warp as mjw  # noqa: E402  (after the config above)
from mujoco_warp._src import types as _warp_types  # noqa: E402  (vec6, the geom-group mask rays() takes)

from batchsim.backends.device import (  # noqa: E402
    DEVICE_ARRAYS,
    FIELD_SHIFT,
    INDEX_SHIFT,
    MAX_INDEX,
    DeviceSystem,
    code_status,
)
from batchsim.hardware import MAX_COMMAND, READ_FIELDS, Status, StepFailures  # noqa: E402
from batchsim.model import RobotSpec  # noqa: E402
from batchsim.sensors import Camera, Lidar, LidarKind  # noqa: E402

log = logging.getLogger("batchsim.warp")

# Warp captures and replays graphs on its CPU device through process-wide state: two systems
# doing so from two threads at once (the shards of one fleet on CPU devices) crash the process
_CPU_GRAPHS = threading.Lock()

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
# what filled up, for the log; and which option's buffers hold it (None: none that can grow)
_OVERFLOWS = {
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
_GROWS = {"nconmax": 0, "njmax": 0}
for _kind, (_what, _option) in _OVERFLOWS.items():
    if _option is not None:
        _GROWS[_option] |= int(_kind)

# what a period changes of MuJoCo's integration state (inputs such as ctrl and mocap it only
# reads), kept at its start; and the whole integration state, carried into grown buffers
_CHANGED = int(mjw.State.PHYSICS | mjw.State.WARMSTART)
_INTEGRATION = int(mjw.State.PHYSICS | mjw.State.USER | mjw.State.WARMSTART)  # no PLUGIN in Warp

# growth: at least this factor, at most that, per re-allocation
_GROW_MIN, _GROW_MAX = 2.0, 8.0
_MEMORY_MARGIN = 0.9  # of the free memory a grown Data may take
_MAX_ELEMENTS = 2**31 - 1  # Warp indexes arrays with 32-bit integers

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
    code_out: wp.array(dtype=wp.int32),
):
    """code_out[w]: the world's failure code (batchsim.backends.device): DIVERGED with the first
    bad entry of qpos, qvel, qacc (NaN or beyond mjMAXVAL), OVERFLOW if a buffer overflowed."""
    w = wp.tid()
    field = int(0)  # noqa: UP018  (int(): a mutable Warp variable, not a constant)
    index = int(0)  # noqa: UP018
    for i in range(qpos.shape[1]):
        x = qpos[w, i]
        if field == 0 and (wp.isnan(x) or wp.abs(x) > maxval):
            field = 1
            index = i
    for i in range(qvel.shape[1]):
        x = qvel[w, i]
        if field == 0 and (wp.isnan(x) or wp.abs(x) > maxval):
            field = 2
            index = i
    for i in range(qacc.shape[1]):
        x = qacc[w, i]
        if field == 0 and (wp.isnan(x) or wp.abs(x) > maxval):
            field = 3
            index = i
    code = int(0)  # noqa: UP018
    if field != 0:
        code = int(Status.DIVERGED) | (field << FIELD_SHIFT) | (wp.min(index, MAX_INDEX) << INDEX_SHIFT)
    if (overflow[w] & overflow_mask) != 0:
        code = code | int(Status.OVERFLOW)
    code_out[w] = code


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
    clock: wp.array(dtype=wp.float64),
    source: wp.array(dtype=wp.int32),
    index: wp.array(dtype=wp.int32),
    nstate: wp.int32,
    state_out: wp.array2d(dtype=wp.float64),
    sensordata_out: wp.array2d(dtype=wp.float64),
    time_out: wp.array(dtype=wp.float64),
):
    """The read() columns, sensordata and time of every world, widened to float64.

    Column c < nstate is read column c, from field source[c] at index[c]; the next
    nsensordata columns are sensordata; the last is the float64 clock.
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
        time_out[w] = clock[w]


@wp.kernel
def _advance_clock(
    dt: wp.float64,
    nstep: wp.int32,
    clock: wp.array(dtype=wp.float64),
    time_out: wp.array(dtype=wp.float32),
):
    """nstep timesteps onto each world's float64 clock, one addition each as mj_step adds them
    (cpu's time to the bit), and MuJoCo Warp's float32 time set from it."""
    w = wp.tid()
    t = clock[w]
    for _ in range(nstep):
        t = t + dt
    clock[w] = t
    time_out[w] = wp.float32(t)


@wp.kernel
def _set_rows(mask: wp.array(dtype=wp.bool), row: wp.array(dtype=Any), out: wp.array2d(dtype=Any)):
    """out[w] = row for the masked worlds (float32, vec3 or quat rows)."""
    w, j = wp.tid()
    if mask[w]:
        out[w, j] = row[j]


@wp.kernel
def _set_clock(
    mask: wp.array(dtype=wp.bool),
    value: wp.float64,
    clock: wp.array(dtype=wp.float64),
    time_out: wp.array(dtype=wp.float32),
):
    w = wp.tid()
    if mask[w]:
        clock[w] = value
        time_out[w] = wp.float32(value)


@wp.kernel
def _gather_poses(
    worlds: wp.array(dtype=wp.int32),
    xpos: wp.array2d(dtype=wp.vec3),
    xquat: wp.array2d(dtype=wp.quat),
    poses_out: wp.array3d(dtype=wp.float32),
):
    """poses_out[i, body] = xpos (3), then xquat (4, MuJoCo's order: w, x, y, z) of world worlds[i]."""
    i, body = wp.tid()
    w = worlds[i]
    p = xpos[w, body]
    q = xquat[w, body]
    for k in range(3):
        poses_out[i, body, k] = p[k]
    for k in range(4):
        poses_out[i, body, 3 + k] = q[k]


@wp.kernel
def _copy_rows(mask: wp.array(dtype=wp.bool), src: wp.array2d(dtype=Any), out: wp.array2d(dtype=Any)):
    w, j = wp.tid()
    if mask[w]:
        out[w, j] = src[w, j]


@wp.kernel
def _copy_items(mask: wp.array(dtype=wp.bool), src: wp.array(dtype=Any), out: wp.array(dtype=Any)):
    w = wp.tid()
    if mask[w]:
        out[w] = src[w]


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


class WarpSystem(DeviceSystem):
    """`nworld` worlds on MuJoCo Warp, one captured graph per control period.

    Options:
      nconmax: contacts per world, on average (MuJoCo Warp pools them over the worlds), to
        start with; None sizes it from a short CPU rollout of the model, with headroom. It
        grows when a period overflows it.
      njmax: constraint rows per world to start with; None sizes it from the same rollout.
        It grows likewise.
      max_data_bytes: the most memory MuJoCo Warp's Data may take when buffers grow; None:
        what the device has free.
      device: a Warp device ("cuda:0", "cpu"); None is Warp's default (the first GPU if
        there is one).
      graph: capture each control period in a graph and replay it; False launches the
        kernels one by one, for debugging.
      deterministic: bitwise-repeatable results on a GPU (MuJoCo Warp's sorted contacts,
        canonical constraint rows and order-invariant atomic sums), slower. Warp's CPU
        device is repeatable either way.

    Attributes (beyond BatchedSystem's):
      nconmax, njmax: the buffer sizes now, after any growth.
    """

    name: ClassVar[str] = "warp"
    OPTIONS: ClassVar[dict[str, Any]] = {
        "nconmax": None,
        "njmax": None,
        "max_data_bytes": None,
        "device": None,
        "graph": True,
        "deterministic": False,
    }

    def __init__(self, spec: RobotSpec, nworld: int, **options: Any):
        super().__init__(spec, nworld, **options)
        sized = None
        if self.options["nconmax"] is None or self.options["njmax"] is None:
            sized = rollout_sizes(self.model)
        self.nconmax = int(self.options["nconmax"] if self.options["nconmax"] is not None else sized[0])
        self.njmax = int(self.options["njmax"] if self.options["njmax"] is not None else sized[1])
        if self.nconmax < 0 or self.njmax < 0:
            raise ValueError(f"nconmax and njmax must be >= 0, got {self.nconmax} and {self.njmax}")
        self._cuda = self.device.is_cuda
        # The host arrays a user sees become pinned memory that the device copies into
        # directly: read() then costs one DMA per array and no host-side copy or conversion.
        self._state_wp = self._host_array(self._readings.shape, wp.float64)
        self._sensor_wp = self._host_array(self._sensor_host.shape, wp.float64)
        self._time_wp = self._host_array(self.time.shape, wp.float64)
        self._ctrl_wp = self._host_array((self.nworld, self.model.nu), wp.float64)
        self._flags_wp = self._host_array((self.nworld,), wp.int32)
        self._bind_readings(self._state_wp.numpy())
        self._bind_sensordata(self._sensor_wp.numpy())
        self.time = self._time_wp.numpy()
        self._ctrl = self._ctrl_wp.numpy()
        self._flags = self._flags_wp.numpy()

    @staticmethod
    def _resolve_device(option: Any) -> Any:
        return wp.get_device(option)

    @staticmethod
    def _put_model(m: mujoco.MjModel, device: Any) -> Any:
        with wp.ScopedDevice(device):
            return mjw.put_model(m)

    @staticmethod
    def available_devices() -> list[str]:
        """Warp's devices for this backend: every CUDA GPU ("cuda:0", ...), else ["cpu"]."""
        gpus = [d.alias for d in wp.get_cuda_devices()]
        return gpus or ["cpu"]

    def _host_array(self, shape: tuple[int, ...], dtype: Any) -> wp.array:
        """A zeroed host array: pinned (page-locked) when the device is a GPU."""
        return wp.zeros(shape, dtype=dtype, device="cpu", pinned=self._cuda)

    # --- engine hooks ---
    def _open(self) -> None:
        m, n = self.model, self.nworld
        self._mjd0 = mjd = self._initial_data()
        self._time0 = float(mjd.time)
        with wp.ScopedDevice(self.device):
            self._m = self._model_on_device
            # failures are read per world from d.overflow; MuJoCo Warp's own printf per
            # overflowing world and step would flood the console
            self._m.opt.warn_overflow = 0
            if self.options["deterministic"]:
                self._m.opt.deterministic = int(mjw.DeterminismType.ALL)
            # the initial state's own contacts and constraints must fit (put_data's rule)
            if mjd.ncon > self.nconmax or mjd.nefc > self.njmax:
                grown = max(self.nconmax, mjd.ncon), max(self.njmax, int(mjd.nefc))
                log.info(
                    "batchsim: warp: the initial state has %d contacts and %d constraint rows; buffers "
                    "start at nconmax %d and njmax %d per world (asked: %d and %d)",
                    mjd.ncon, mjd.nefc, *grown, self.nconmax, self.njmax,
                )
                self.nconmax, self.njmax = grown
            self._d = mjw.put_data(m, mjd, nworld=n, nconmax=self.nconmax, njmax=self.njmax)
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
                    ("xpos", wp.vec3),  # body poses of the initial state, as cpu's reset computes them
                    ("xquat", wp.quat),
                )
                if getattr(mjd, field).size
            }
            self._clock = wp.full(n, self._time0, dtype=wp.float64)
            self._parked_dev = wp.zeros(n, dtype=wp.int32)
            self._mask_dev = wp.zeros(n, dtype=wp.bool)
            nread = self._readings.shape[1]
            source = np.zeros(nread, np.int32)
            index = np.zeros(nread, np.int32)
            for c, col in enumerate(self._columns):
                source[c], index[c] = READ_FIELDS.index(col.source), col.index
            self._source = wp.array(source, dtype=wp.int32)
            self._index = wp.array(index, dtype=wp.int32)
            # the period's start, kept on the device: to repeat it, or to read a failed world
            self._start = {
                "state": wp.zeros((n, mujoco.mj_stateSize(m, _CHANGED)), dtype=wp.float32),
                "qfrc_actuator": wp.zeros_like(self._d.qfrc_actuator),
                "sensordata": wp.zeros_like(self._d.sensordata),
                "clock": wp.zeros_like(self._clock),
            }
            # failed worlds' readings from the start, gathered apart from what read() shows
            self._failed_readings = (
                wp.zeros(self._readings.shape, dtype=wp.float64),
                wp.zeros(self._sensor_host.shape, dtype=wp.float64),
                wp.zeros(n, dtype=wp.float64),
            )
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
            self._keep_start()  # compile its kernels now rather than inside a capture
        self._graphs: dict[int, Any] = {}
        self._ncols = self._readings.shape[1] + self._sensor_host.shape[1] + 1

    def _close(self) -> None:
        self._graphs.clear()
        for name in (
            "_m",
            "_d",
            "_mjd0",
            "_initial_rows",
            "_clock",
            "_parked_dev",
            "_mask_dev",
            "_source",
            "_index",
            "_start",
            "_failed_readings",
        ):
            self.__dict__.pop(name, None)

    def _ctrl_host(self) -> np.ndarray:
        return self._ctrl

    def _upload_ctrl(self) -> None:
        with wp.ScopedDevice(self.device):
            if self._cuda:
                wp.copy(self._ctrl_dev, self._ctrl_wp)
            wp.launch(  # the device named: ScopedDevice is process-wide, and shards write at once
                _narrow_ctrl,
                dim=self._ctrl.shape,
                inputs=[self._ctrl_dev, self._parked_dev],
                outputs=[self._d.ctrl],
                device=self.device,
            )

    def _read(self) -> None:
        with wp.ScopedDevice(self.device):
            self._gather_on_device(self._state_dev, self._sensor_dev, self._time_dev)
            if self._cuda:
                wp.copy(self._state_wp, self._state_dev)
                if self._sensor_host.size:
                    wp.copy(self._sensor_wp, self._sensor_dev)
                wp.copy(self._time_wp, self._time_dev)
            wp.synchronize_device(self.device)

    def _gather_on_device(self, state_out: wp.array, sensordata_out: wp.array, time_out: wp.array) -> None:
        d = self._d
        wp.launch(
            _gather_state,
            dim=(self.nworld, self._ncols),
            inputs=[
                d.qpos,
                d.qvel,
                d.qfrc_actuator,
                d.sensordata,
                self._clock,
                self._source,
                self._index,
                self._readings.shape[1],
            ],
            outputs=[state_out, sensordata_out, time_out],
            device=self.device,  # named: a sharded fleet reads its shards at once, and ScopedDevice is process-wide
        )

    def _step(self, nstep: int) -> StepFailures | None:
        while True:
            self._launch(nstep)
            codes = self._flags
            if not codes.any():
                return None
            live = (codes != 0) & ~self.frozen
            if not live.any():
                return None
            if not self._grow(codes, live):
                return self._failures(np.flatnonzero(live), codes)
            # grown, and every world back at the period's start: run the period again

    def _launch(self, nstep: int) -> None:
        serial = _CPU_GRAPHS if self.options["graph"] and not self._cuda else contextlib.nullcontext()
        with wp.ScopedDevice(self.device), serial:
            if self.options["graph"]:
                graph = self._graphs.get(nstep)
                if graph is None:
                    graph = self._graphs[nstep] = self._capture(nstep)
                wp.capture_launch(graph)
            else:
                self._period(nstep)
            if self._cuda:
                wp.copy(self._flags_wp, self._flags_dev)
            wp.synchronize_device(self.device)

    def _period(self, nstep: int) -> None:
        m, d = self._m, self._d
        self._keep_start()
        for _ in range(nstep):
            mjw.step(m, d)
        wp.launch(_advance_clock, dim=self.nworld, inputs=[self.dt, nstep], outputs=[self._clock, d.time])
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

    # --- the period's start: kept, restored ---
    def _keep_start(self) -> None:
        """Copy what a period changes (mjSTATE_PHYSICS, the warmstart, and the derived fields
        read() gathers) of every world, on the device."""
        d, start = self._d, self._start
        mjw.get_state(self._m, d, start["state"], _CHANGED)
        wp.copy(start["qfrc_actuator"], d.qfrc_actuator)
        if d.sensordata.size:
            wp.copy(start["sensordata"], d.sensordata)
        wp.copy(start["clock"], self._clock)

    def _restore_start(self, mask: wp.array | None) -> None:
        """Put the masked worlds (None: all) back where the period started."""
        d, start = self._d, self._start
        mjw.set_state(self._m, d, start["state"], _CHANGED, active=mask)
        if mask is None:
            wp.copy(d.qfrc_actuator, start["qfrc_actuator"])
            if d.sensordata.size:
                wp.copy(d.sensordata, start["sensordata"])
            wp.copy(self._clock, start["clock"])
            return
        for field in ("qfrc_actuator", "sensordata"):
            out = getattr(d, field)
            if out.size:
                wp.launch(_copy_rows, dim=out.shape, inputs=[mask, start[field]], outputs=[out])
        wp.launch(_copy_items, dim=self.nworld, inputs=[mask, start["clock"]], outputs=[self._clock])

    def _failures(self, worlds: np.ndarray, codes: np.ndarray) -> StepFailures:
        """The failed worlds, read as they were when the period started."""
        mask = np.zeros(self.nworld, bool)
        mask[worlds] = True
        with wp.ScopedDevice(self.device):
            overflow = self._d.overflow.numpy()[worlds] & _BUFFER_OVERFLOWS
            self._mask_dev.assign(mask)
            self._restore_start(self._mask_dev)  # they are parked right after: no harm done
            self._gather_on_device(*self._failed_readings)
            state, sensordata, time = (a.numpy()[worlds] for a in self._failed_readings)
        self._apply_signs(state)  # an engine gather, unsigned like _read()'s
        return StepFailures(
            worlds=worlds,
            status=code_status(codes[worlds]),
            reasons=self._failure_reasons(codes[worlds], lambda i: self._overflow_reason(int(overflow[i]))),
            readings=state,
            sensordata=sensordata,
            time=time,
        )

    def _overflow_reason(self, bits: int) -> str:
        kinds = [(what, option) for kind, (what, option) in _OVERFLOWS.items() if bits & int(kind)]
        said = "; ".join(what + (f" ({option})" if option else "") for what, option in kinds)
        if any(option for _, option in kinds) and self._cannot_grow:
            said += f"; {self._cannot_grow}"
        return said or "a buffer overflowed"

    # --- growing the buffers ---
    _cannot_grow = ""  # why the last growth was impossible, for the failure lines

    def _grow(self, codes: np.ndarray, live: np.ndarray) -> bool:
        """Grow the buffers that overflowed in this period and restore every world to its start.
        False if nothing that overflowed can grow, or there is not the memory for it."""
        self._cannot_grow = ""
        overflowed = live & ((codes & int(Status.OVERFLOW)) != 0)
        if not overflowed.any():
            return False
        d = self._d
        bits = int(np.bitwise_or.reduce(d.overflow.numpy()[overflowed] & _BUFFER_OVERFLOWS))
        grows = {option: bits & mask for option, mask in _GROWS.items() if bits & mask}
        if not grows:
            return False
        # MuJoCo Warp's counters go on counting past the buffers: what the last step needed
        need = {
            "nconmax": math.ceil(max(int(d.ncollision.numpy()[0]), int(d.nacon.numpy()[0])) / self.nworld),
            "njmax": int(d.nefc.numpy().max()),
        }
        now = {"nconmax": self.nconmax, "njmax": self.njmax}
        plans = []
        for grow in (True, False):  # ample first; then only what the counters ask
            size = dict(now)
            for option in grows:
                lo = max(now[option] + 1, need[option])
                size[option] = _grown(now[option], need[option]) if grow else lo
            if size not in plans:
                plans.append(size)
        limit = self._memory_for_data()
        for size in plans:
            nbytes, elements = _data_size(d, size["nconmax"] / max(now["nconmax"], 1), size["njmax"] / max(now["njmax"], 1))
            if nbytes <= limit and elements <= _MAX_ELEMENTS:
                break
        else:
            size = plans[-1]
            what = "the device's free memory" if self.options["max_data_bytes"] is None else "max_data_bytes"
            self._cannot_grow = (
                f"growing {' and '.join(f'{o} to {size[o]}' for o in grows)} per world needs "
                f"{nbytes / 2**30:.2f} GiB, more than {what} allows ({limit / 2**30:.2f} GiB)"
            )
            return False
        self._reallocate(size["nconmax"], size["njmax"])
        names = " and ".join(
            " and ".join(what for kind, (what, option) in _OVERFLOWS.items() if option == o and bits & int(kind))
            + f" ({o})"
            for o in grows
        )
        log.warning(
            "batchsim: warp: %s overflowed in %d of %d worlds; grew %s per world and repeated the period",
            names,
            int(overflowed.sum()),
            self.nworld,
            " and ".join(f"{o} {now[o]} -> {size[o]}" for o in grows),
        )
        return True

    def _reallocate(self, nconmax: int, njmax: int) -> None:
        """New Data with these buffers, every world at the period's start carried over; the
        arrays device_arrays() hands out stay the same objects."""
        m, n, old = self.model, self.nworld, self._d
        with wp.ScopedDevice(self.device):
            self._restore_start(None)
            state = wp.zeros((n, mujoco.mj_stateSize(m, _INTEGRATION)), dtype=wp.float32)
            mjw.get_state(self._m, old, state, _INTEGRATION)
            new = mjw.make_data(m, nworld=n, nconmax=nconmax, njmax=njmax)
            mjw.set_state(self._m, new, state, _INTEGRATION)
            for field in DEVICE_ARRAYS:  # same values; keep the arrays users may hold
                setattr(new, field, getattr(old, field))
            wp.synchronize_device(self.device)
        self._d = new
        self.nconmax, self.njmax = nconmax, njmax
        self._graphs.clear()  # they launch on the old buffers: capture again
        self._sensor_graphs = None  # likewise
        del old

    def _memory_for_data(self) -> float:
        """Bytes a grown Data may take: max_data_bytes, else a margin under what is free."""
        if self.options["max_data_bytes"] is not None:
            return float(self.options["max_data_bytes"])
        if self._cuda:
            return _MEMORY_MARGIN * self.device.free_memory
        try:  # Warp's CPU device: the host's available memory (Linux)
            return _MEMORY_MARGIN * os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
            return math.inf

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
            wp.launch(
                _set_clock, dim=self.nworld, inputs=[self._mask_dev, self._time0], outputs=[self._clock, d.time]
            )
            self._parked_dev.assign(self.frozen.astype(np.int32))

    def _body_poses(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # gathered on the device, then one copy of just those worlds to the host
        with wp.ScopedDevice(self.device):
            index = wp.array(worlds.astype(np.int32), dtype=wp.int32)
            poses = wp.empty((len(worlds), self.model.nbody, 7), dtype=wp.float32)
            if len(worlds):
                wp.launch(
                    _gather_poses,
                    dim=(len(worlds), self.model.nbody),
                    inputs=[index, self._d.xpos, self._d.xquat],
                    outputs=[poses],
                    device=self.device,
                )
            host = poses.numpy()
        return host[..., :3], host[..., 3:]

    # --- for users who stay on the device ---
    def device_arrays(self) -> dict[str, wp.array]:
        """The simulation's live Warp arrays, zero copy: qpos, qvel, qfrc_actuator, sensordata,
        ctrl `(nworld, ...)` and time `(nworld,)`, float32, on `self.device`.

        They are the buffers MuJoCo Warp steps in place, valid until cleanup() (a buffer
        growth keeps them); pass them to other frameworks with DLPack (`torch.from_dlpack(a)`,
        `jax.dlpack.from_dlpack(a)`). Rows of frozen worlds (see `status`) are parked and
        meaningless until reset. `time` is the engine's float32 clock, set from `sim.time`
        (float64) at the end of each period.
        """
        d = self._d
        return {f: getattr(d, f) for f in DEVICE_ARRAYS}

    # --- cameras and lidars: MuJoCo Warp's ray-traced rendering and ray casting ---
    sensors_batched: ClassVar[bool] = True  # every world in one launch, whichever are asked for
    _render_contexts: dict[str, Any] | None = None  # per camera: (render context, rgb, depth, host rgb, host depth)
    _lidar_buffers: dict[str, Any] | None = None  # per lidar: its rays and results, on the device and host
    # per camera or lidar: its launches captured in a graph (they take this Data's arrays:
    # dropped when the buffers grow)
    _sensor_graphs: dict[str, Any] | None = None
    _com_pos: bool | None = None  # whether a camera or light tracks a centre of mass (com_pos needed)

    def _sensor_kinematics(self, cameras: bool) -> None:
        """Positions of bodies, geoms and sites (and cameras, lights) from the current qpos.

        After a step they describe the state before its last substep, and after a reset they
        are stale; images and scans show the current state, as on cpu.
        """
        m, d = self._m, self._d
        mjw.kinematics(m, d)
        if cameras:
            if self._com_pos is None:
                modes = (int(mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM), int(mujoco.mjtCamLight.mjCAMLIGHT_TARGETBODYCOM))
                self._com_pos = bool(np.isin(self.model.cam_mode, modes).any() or np.isin(self.model.light_mode, modes).any())
            if self._com_pos:
                mjw.com_pos(m, d)
            mjw.camlight(m, d)

    def _run_sensor(self, name: str, program: Any) -> None:
        """Run `program` (a camera's or lidar's launches, on buffers fixed until they grow). With
        graphs on, it runs eagerly the first time (kernels compile, the renderer specializes),
        is captured then, and is replayed after: one launch per call, not ten launches'
        argument packing in Python (a render of 1 world at 4x4 on Warp's CPU device: 1.1 ms a
        call launched one by one, 30 us replayed)."""
        if not self.options["graph"]:
            program()
            return
        if self._sensor_graphs is None:
            self._sensor_graphs = {}
        serial = _CPU_GRAPHS if not self._cuda else contextlib.nullcontext()
        with serial:
            graph = self._sensor_graphs.get(name)
            if graph is None:
                program()
                with wp.ScopedCapture(device=self.device) as capture:
                    program()
                self._sensor_graphs[name] = capture.graph
            else:
                wp.capture_launch(graph)

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

            def program() -> None:
                self._sensor_kinematics(cameras=True)
                mjw.refit_bvh(self._m, self._d, rc)
                mjw.render(self._m, self._d, rc)
                wp.launch(_unpack_frames, dim=depth.shape, inputs=[rc.rgb_data, rc.depth_data], outputs=[rgb, depth])

            self._run_sensor(f"camera {camera.name}", program)
        return rgb, depth

    def _render_frames(self, camera: Camera, worlds: np.ndarray, copy: bool) -> tuple[np.ndarray, np.ndarray]:
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
        if len(worlds) == self.nworld:  # every world: the buffers themselves, or one copy of them
            return (rgb_np.copy(), depth_np.copy()) if copy else (rgb_np, depth_np)
        return rgb_np[worlds], depth_np[worlds]  # fancy indexing: a copy

    def _device_ranges(self, lidar: Lidar) -> wp.array:
        """Every world's (nworld, nray) float32 REP 117 ranges on the device, overwritten by the next
        scan of this lidar; a rangefinder lidar's are its sensordata's, uploaded."""
        if lidar.kind is LidarKind.RANGEFINDER:
            return wp.array(self._ranges(lidar, np.arange(self.nworld)), dtype=wp.float32, device=self.device)
        return self._lidar_cast(lidar)["ranges"]

    def _cast_ranges(self, lidar: Lidar, worlds: np.ndarray, copy: bool) -> np.ndarray:
        b = self._lidar_cast(lidar)
        host = b["host"]
        with wp.ScopedDevice(self.device):
            if self._cuda:
                wp.copy(host, b["ranges"])  # one copy, into pinned memory: a DMA
            else:
                host = b["ranges"]
            wp.synchronize_device(self.device)
        ranges = host.numpy()
        if len(worlds) < self.nworld:
            return ranges[worlds]  # fancy indexing: a copy
        return ranges.copy() if copy else ranges

    def _lidar_cast(self, lidar: Lidar) -> dict[str, wp.array]:
        """Cast `lidar`'s rays in every world now; its buffers, "ranges" holding the REP 117 ranges."""
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
                    "ranges": wp.zeros(shape, dtype=wp.float32),
                    "host": self._host_array(shape, wp.float32),
                }
            b = buffers
            everything = _warp_types.vec6(-1.0, -1.0, -1.0, -1.0, -1.0, -1.0)  # every geom group

            def program() -> None:
                self._sensor_kinematics(cameras=False)
                wp.launch(
                    _lidar_rays,
                    dim=shape,
                    inputs=[self._d.site_xpos, self._d.site_xmat, lidar.site_id, b["directions"]],
                    outputs=[b["pnt"], b["vec"]],
                )
                mjw.rays(self._m, self._d, b["pnt"], b["vec"], everything, True, b["exclude"], b["dist"], b["geomid"], b["normal"])
                # REP 117 on the device: the host gets float32 ranges in one copy, nothing left to convert
                wp.launch(
                    _lidar_ranges,
                    dim=shape,
                    inputs=[b["dist"], float(lidar.range_min), float(lidar.range_max)],
                    outputs=[b["ranges"]],
                )

            self._run_sensor(f"lidar {lidar.name}", program)
        return b

    def _close_sensors(self) -> None:
        self._render_contexts = self._lidar_buffers = self._sensor_graphs = None


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


@wp.kernel
def _lidar_ranges(
    dist: wp.array2d(dtype=wp.float32),
    range_min: wp.float32,
    range_max: wp.float32,
    ranges_out: wp.array2d(dtype=wp.float32),
):
    """REP 117 ranges from ray distances (< 0: no hit), as Lidar.ranges on the host: +inf for no
    hit or beyond range_max, -inf closer than range_min."""
    w, r = wp.tid()
    x = dist[w, r]
    if x < wp.float32(0.0) or x > range_max:
        ranges_out[w, r] = wp.inf
    elif x < range_min:
        ranges_out[w, r] = -wp.inf
    else:
        ranges_out[w, r] = x


def _grown(now: int, need: int) -> int:
    """The new size for a buffer of `now` that needed `need`: at least twice, more where the
    counters ask for more (with a quarter on top), at most _GROW_MAX times."""
    want = max(math.ceil(_GROW_MIN * max(now, 1)), math.ceil(1.25 * need))
    return int(min(want, math.ceil(_GROW_MAX * max(now, 1))))


def _data_size(d: Any, con_ratio: float, j_ratio: float) -> tuple[float, int]:
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
