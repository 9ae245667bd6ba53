"""WarpSystem: `nworld` worlds on MuJoCo Warp, one captured graph per control period (the
package's docstring tells the whole design): the engine hooks, the period kept at its start
and restored, failures gathered, buffers re-allocated when they grow.
"""

from __future__ import annotations

import contextlib
import logging
from typing import Any, ClassVar

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp

from batchsim.backends import footprint
from batchsim.backends.device import DEVICE_ARRAYS, DeviceSystem, code_status
from batchsim.backends.warp.buffers import (
    BUFFER_OVERFLOWS,
    growable,
    grown_names,
    memory_for_data,
    overflow_reason,
    plan_growth,
    rollout_sizes,
)
from batchsim.backends.warp.device_io import WarpDeviceIO
from batchsim.backends.warp.fields import WarpFields
from batchsim.backends.warp.host import WarpHost
from batchsim.backends.warp.kernels import (
    CPU_GRAPHS,
    advance_clock,
    check_worlds,
    copy_items,
    copy_rows,
    gather_poses,
    hold_base_velocity,
    rotate_base_velocity,
)
from batchsim.backends.warp.reset import WarpReset
from batchsim.backends.warp.sensors import WarpSensors
from batchsim.backends.warp.transfers import WarpTransfers
from batchsim.backends.warp.wrench import WarpWrenches
from batchsim.model import RobotSpec
from batchsim.types import MAX_COMMAND, READ_FIELDS, Status, StepFailures

log = logging.getLogger("batchsim.warp")

# what a period changes of MuJoCo's integration state (inputs such as ctrl and mocap it only
# reads), kept at its start; and the whole integration state, carried into grown buffers
_CHANGED = int(mjw.State.PHYSICS | mjw.State.WARMSTART)
_INTEGRATION = int(mjw.State.PHYSICS | mjw.State.USER | mjw.State.WARMSTART)  # no PLUGIN in Warp


class WarpSystem(
    WarpHost, WarpTransfers, WarpWrenches, WarpSensors, WarpFields, WarpDeviceIO, WarpReset, DeviceSystem
):
    """`nworld` worlds on MuJoCo Warp, one captured graph per control period.

    Options:
      nconmax: contacts per world, on average (MuJoCo Warp pools them over the worlds), to
        start with; None sizes it from a short CPU rollout of the model, with headroom. It
        grows when a period overflows it.
      njmax: constraint rows per world to start with; None sizes it from the same rollout.
        It grows likewise.
      max_data_bytes: the most memory MuJoCo Warp's Data may take when buffers grow; None:
        what the device has free.
      device: a Warp device ("cuda:0", "cpu"); None is Warp's default (the first GPU, if any).
      graph: capture each control period in a graph and replay it; False launches the
        kernels one by one, for debugging.
      deterministic: bitwise-repeatable results on a GPU (MuJoCo Warp's sorted contacts,
        canonical constraint rows and order-invariant atomic sums), slower. Warp's CPU
        device is repeatable either way.

    Attributes (beyond BatchedSystem's):
      nconmax, njmax: the buffer sizes now, after any growth.
    """

    name: ClassVar[str] = "warp"
    physics_memory = staticmethod(footprint.warp)
    OPTIONS: ClassVar[dict[str, Any]] = {
        "nconmax": None,
        "njmax": None,
        "max_data_bytes": None,
        "device": None,
        "graph": True,
        "deterministic": False,
    }
    OPTION_TYPES: ClassVar[dict[str, type]] = {
        "nconmax": int,
        "njmax": int,
        "max_data_bytes": float,
        "device": object,  # _resolve_device takes a name or a warp Device
    }
    OPTION_MINIMA: ClassVar[dict[str, float]] = {"nconmax": 0, "njmax": 0, "max_data_bytes": 1}

    def __init__(self, spec: RobotSpec, nworld: int, **options: Any):
        super().__init__(spec, nworld, **options)
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
        # the host's ctrl, float32 as on the device: what commands through PIDs, scaling, mimic
        # joints or transmissions become on the host, and what resets and parks upload
        self._ctrl_wp = self._host_array((self.nworld, self.model.nu), wp.float32)
        self._flags_wp = self._host_array((self.nworld,), wp.int32)
        # plain commands go up as they are, from pinned memory (warp/transfers.py); the rows the
        # device's check rejected come back in `_rejected`
        self._command_wp = self._host_array(self._command.shape, wp.float64)
        self._command_wp.numpy()[:] = self._command
        self._rejected_wp = self._host_array((self.nworld,), wp.bool)
        self._bind_readings(self._state_wp.numpy())
        self._bind_sensordata(self._sensor_wp.numpy())
        self.time = self._time_wp.numpy()
        self._ctrl = self._ctrl_wp.numpy()
        self._flags = self._flags_wp.numpy()
        self._command = self._command_wp.numpy()
        self._rejected = self._rejected_wp.numpy()

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
                source[c], index[c] = READ_FIELDS.index(col.source.value), col.index
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
                self._ctrl_dev = wp.zeros(self._ctrl.shape, dtype=wp.float32)
                self._flags_dev = wp.zeros(n, dtype=wp.int32)
                self._command_dev = wp.zeros(self._command.shape, dtype=wp.float64)
                self._rejected_dev = wp.zeros(n, dtype=wp.bool)
            else:  # Warp's CPU device: the kernels read and write the host arrays themselves
                self._state_dev, self._sensor_dev, self._time_dev = (
                    self._state_wp,
                    self._sensor_wp,
                    self._time_wp,
                )
                self._ctrl_dev, self._flags_dev = self._ctrl_wp, self._flags_wp
                self._command_dev, self._rejected_dev = self._command_wp, self._rejected_wp
            self._actuator_dev = wp.array(self._ctrl_index.astype(np.int32), dtype=wp.int32)
            self._ctrl_behind = False
            # the base velocity's target (batchsim.base_velocity): staged on the host, copied to the
            # device, rotated into the world at each period's start; NaN until write() stages one
            self._held_host = self._held_dev = self._held_world = None
            if self.base_velocity is not None:
                self._held_wp = self._host_array((n, 3), wp.float32)
                self._held_host = self._held_wp.numpy()
                self._held_host[:] = np.nan
                self._held_dev = wp.array(self._held_host, dtype=wp.float32) if self._cuda else self._held_wp
                self._held_world = wp.zeros((n, 3), dtype=wp.float32)
            self._keep_start()  # compile its kernels now rather than inside a capture
        self._graphs: dict[int | str, Any] = {}  # per period length; and the reset (warp/reset.py)
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
            "_held_dev",
            "_held_world",
            "_actuator_dev",
        ):
            self.__dict__.pop(name, None)

    def _stage_base_velocity(self, target: np.ndarray) -> None:
        np.copyto(self._held_host, target, casting="same_kind")
        if self._cuda:  # pinned memory: the copy is queued ahead of the next period's graph
            with wp.ScopedDevice(self.device):
                wp.copy(self._held_dev, self._held_wp)

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
        if self._replay_captured(nstep):  # the flags' copy to the host is in it
            self._while_stepping()
            wp.synchronize_device(self.device)
            return
        serial = CPU_GRAPHS if self.options["graph"] and not self._cuda else contextlib.nullcontext()
        with wp.ScopedDevice(self.device), serial:
            if self.options["graph"]:
                graph = self._graphs.get(nstep)
                if graph is None:
                    graph = self._graphs[nstep] = self._capture(nstep)
                wp.capture_launch(graph)  # the flags' copy to the host is in it
            else:
                self._period(nstep)
                if self._cuda:
                    wp.copy(self._flags_wp, self._flags_dev)
            self._while_stepping()
            wp.synchronize_device(self.device)

    def _period(self, nstep: int) -> None:
        m, d = self._m, self._d
        self._keep_start()
        drive = self.base_velocity
        if drive is not None:
            inputs = [d.qpos, self._held_dev, drive.qposadr]
            wp.launch(rotate_base_velocity, dim=self.nworld, inputs=inputs, outputs=[self._held_world])
        for _ in range(nstep):
            if drive is not None:  # before every substep, as upstream's simulation applies it
                wp.launch(hold_base_velocity, dim=self.nworld, inputs=[self._held_world, drive.dofadr], outputs=[d.qvel])
            mjw.step(m, d)
        wp.launch(advance_clock, dim=self.nworld, inputs=[self.dt, nstep], outputs=[self._clock, d.time])
        wp.launch(
            check_worlds,
            dim=self.nworld,
            inputs=[d.qpos, d.qvel, d.qacc, d.overflow, BUFFER_OVERFLOWS, float(MAX_COMMAND)],
            outputs=[self._flags_dev],
        )

    def _capture(self, nstep: int) -> Any:
        with wp.ScopedCapture(device=self.device) as capture:
            self._period(nstep)
            if self._cuda:  # one call fewer a period: the check's flags come back inside the graph
                wp.copy(self._flags_wp, self._flags_dev)
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
                wp.launch(copy_rows, dim=out.shape, inputs=[mask, start[field]], outputs=[out])
        wp.launch(copy_items, dim=self.nworld, inputs=[mask, start["clock"]], outputs=[self._clock])

    def _failures(self, worlds: np.ndarray, codes: np.ndarray) -> StepFailures:
        """The failed worlds, read as they were when the period started."""
        mask = np.zeros(self.nworld, bool)
        mask[worlds] = True
        with wp.ScopedDevice(self.device):
            overflow = self._d.overflow.numpy()[worlds] & BUFFER_OVERFLOWS
            self._mask_dev.assign(mask)
            self._restore_start(self._mask_dev)  # they are parked right after: no harm done
            self._gather_on_device(*self._failed_readings)
            state, sensordata, time = (a.numpy()[worlds] for a in self._failed_readings)
        self._finish_gather(state)  # an engine gather, unsigned like _read()'s
        return StepFailures(
            worlds=worlds,
            status=code_status(codes[worlds]),
            reasons=self._failure_reasons(codes[worlds], lambda i: self._overflow_reason(int(overflow[i]))),
            readings=state,
            sensordata=sensordata,
            time=time,
        )

    def _overflow_reason(self, bits: int) -> str:
        return overflow_reason(bits, self._cannot_grow)

    # --- growing the buffers (batchsim.backends.warp.buffers) ---
    _cannot_grow = ""  # why the last growth was impossible, for the failure lines

    def _grow(self, codes: np.ndarray, live: np.ndarray) -> bool:
        """Grow the buffers that overflowed in this period and restore every world to its start.
        False if nothing that overflowed can grow, or there is not the memory for it."""
        self._cannot_grow = ""
        overflowed = live & ((codes & int(Status.OVERFLOW)) != 0)
        if not overflowed.any():
            return False
        bits = int(np.bitwise_or.reduce(self._d.overflow.numpy()[overflowed] & BUFFER_OVERFLOWS))
        grows = growable(bits)
        if not grows:
            return False
        now = {"nconmax": self.nconmax, "njmax": self.njmax}
        max_bytes = self.options["max_data_bytes"]
        limited_by = "the device's free memory" if max_bytes is None else "max_data_bytes"
        size, self._cannot_grow = plan_growth(
            self._d, self.nworld, now, grows, memory_for_data(self.device, max_bytes), limited_by
        )
        if size is None:
            return False
        self._reallocate(size["nconmax"], size["njmax"])
        log.warning(
            "batchsim: warp: %s overflowed in %d of %d worlds; grew %s per world and repeated the period",
            grown_names(bits, grows),
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

    def _qstate(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with wp.ScopedDevice(self.device):
            return self._d.qpos.numpy()[worlds], self._d.qvel.numpy()[worlds]

    def _set_qstate(self, worlds: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        # a rare teleport: whole arrays down and up, written in place (captured graphs keep their pointers)
        with wp.ScopedDevice(self.device):
            for array, rows in ((self._d.qpos, qpos), (self._d.qvel, qvel)):
                host = array.numpy()
                host[worlds] = rows
                array.assign(host)

    def _body_poses(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # gathered on the device, then one copy of just those worlds to the host
        with wp.ScopedDevice(self.device):
            index = wp.array(worlds.astype(np.int32), dtype=wp.int32)
            poses = wp.empty((len(worlds), self.model.nbody, 7), dtype=wp.float32)
            if len(worlds):
                wp.launch(
                    gather_poses,
                    dim=(len(worlds), self.model.nbody),
                    inputs=[index, self._d.xpos, self._d.xquat],
                    outputs=[poses],
                    device=self.device,
                )
            host = poses.numpy()
        return host[..., :3], host[..., 3:]

    _pose_host: tuple[wp.array, wp.array] | None = None

    def _pose_rows(self) -> tuple[np.ndarray, np.ndarray]:
        # every world's, as tf asks each period: the engine's own arrays on Warp's CPU device, else
        # one copy of each into pinned host arrays kept for it (no gather, no allocation), float32
        d = self._d
        if not self._cuda:
            return d.xpos.numpy(), d.xquat.numpy()
        with wp.ScopedDevice(self.device):
            if self._pose_host is None:
                self._pose_host = (self._host_array(d.xpos.shape, wp.vec3), self._host_array(d.xquat.shape, wp.quat))
            wp.copy(self._pose_host[0], d.xpos)
            wp.copy(self._pose_host[1], d.xquat)
            wp.synchronize_device(self.device)
        return self._pose_host[0].numpy(), self._pose_host[1].numpy()

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
