"""WarpEngine: `nworld` worlds on MuJoCo Warp, one captured graph per control period (the
package's docstring tells the whole design). The engine answers the contract's calls and owns
a helper for each job, built at open with what it needs: the worlds on the device
(DeviceWorlds) and the graphs captured on them (Graphs), shared; the transfers of read() and
write(), the period and its start, the reset, body poses, wrenches, the device path, and the
cameras and lidars. Here: their calls conducted, failures gathered, buffers grown.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any, ClassVar

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp

from batchsim.backends import footprint
from batchsim.backends.device import DEVICE_ARRAYS, DeviceEngine, code_status
from batchsim.backends.warp import host
from batchsim.backends.warp.buffers import (
    BUFFER_OVERFLOWS,
    growable,
    grown_data,
    grown_names,
    memory_for_data,
    overflow_reason,
    plan_growth,
    rollout_sizes,
)
from batchsim.backends.warp.device_io import DeviceIO
from batchsim.backends.warp.fields import batched_fields, set_world_fields
from batchsim.backends.warp.period import Period
from batchsim.backends.warp.poses import Poses
from batchsim.backends.warp.reset import Reset
from batchsim.backends.warp.sensors import Sensors
from batchsim.backends.warp.transfers import COMMANDS, READ, WRITE, Transfers
from batchsim.backends.warp.worlds import DeviceWorlds, Graphs
from batchsim.backends.warp.wrench import Wrenches
from batchsim.engine import EngineBuffers
from batchsim.model import RobotSpec
from batchsim.sensors import Camera, Lidar, LidarKind
from batchsim.types import HeldBase, Status, StepFailures

log = logging.getLogger("batchsim.warp")


class WarpEngine(DeviceEngine):
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

    Attributes (beyond DeviceEngine's):
      nconmax, njmax: the buffer sizes now, after any growth.
    """

    name: ClassVar[str] = "warp"
    physics_memory = staticmethod(footprint.warp)
    sensors_batched: ClassVar[bool] = True  # every world in one launch, whichever are asked for
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

    _host: host.HostArrays | None = None  # the host arrays bound (bind)
    _sensors: Sensors | None = None  # made on the first render or scan
    _cannot_grow = ""  # why the last growth was impossible, for the failure lines

    def __init__(self, spec: RobotSpec, nworld: int, **options: Any):
        super().__init__(spec, nworld, **options)
        sized = None
        if self.options["nconmax"] is None or self.options["njmax"] is None:
            sized = rollout_sizes(self.model)
        self.nconmax = int(self.options["nconmax"] if self.options["nconmax"] is not None else sized[0])
        self.njmax = int(self.options["njmax"] if self.options["njmax"] is not None else sized[1])
        self._cuda = self.device.is_cuda
        self._graphs = Graphs(self.device, self.options["graph"])  # per period length; the transfers', the reset's

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

    @classmethod
    def variable_fields(cls, m: mujoco.MjModel) -> frozenset[str]:
        """MuJoCo Warp's batched Model and Option arrays that mirror an MjModel field of `m`."""
        return batched_fields(m)

    # --- the host arrays ---
    def bind(self, buffers: EngineBuffers) -> EngineBuffers:
        """The first call: pinned arrays (on a GPU) in place of the contract's, holding their values,
        which the device copies into directly (read() costs one DMA per array, no host-side copy
        or conversion). A later one (a fleet's shard): the fleet's arrays, page-locked and read
        into as they are (warp/host.py)."""
        if self._host is None:
            self._host, buffers = host.pin(buffers, self._cuda)
        else:
            self._host = host.follow(self._host, buffers, self.device, self)
        self.buffers = buffers
        return buffers

    # --- lifecycle ---
    def open(self, *, held_base: HeldBase | None = None, varied: tuple[str, ...] = ()) -> None:
        m, n = self.model, self.nworld
        mjd = self._initial_data()
        with wp.ScopedDevice(self.device):
            mw = self._model_on_device
            # failures are read per world from d.overflow; MuJoCo Warp's own printf per
            # overflowing world and step would flood the console
            mw.opt.warn_overflow = 0
            if self.options["deterministic"]:
                mw.opt.deterministic = int(mjw.DeterminismType.ALL)
            # the initial state's own contacts and constraints must fit (put_data's rule)
            if mjd.ncon > self.nconmax or mjd.nefc > self.njmax:
                grown = max(self.nconmax, mjd.ncon), max(self.njmax, int(mjd.nefc))
                log.info(
                    "batchsim: warp: the initial state has %d contacts and %d constraint rows; buffers "
                    "start at nconmax %d and njmax %d per world (asked: %d and %d)",
                    mjd.ncon, mjd.nefc, *grown, self.nconmax, self.njmax,
                )
                self.nconmax, self.njmax = grown
            self._worlds = w = DeviceWorlds(
                model=m,
                m=mw,
                d=mjw.put_data(m, mjd, nworld=n, nconmax=self.nconmax, njmax=self.njmax),
                device=self.device,
                nworld=n,
                clock=wp.full(n, float(mjd.time), dtype=wp.float64),
                parked=wp.zeros(n, dtype=wp.int32),
                mask=wp.zeros(n, dtype=wp.bool),
            )
            self._transfers = Transfers(w, self._host, self.buffers)
            self._period = Period(w, self._graphs, self.dt, held_base)
            self._reset = Reset(w, self._graphs, mjd)
            self._period.keep_start()  # compile its kernels now rather than inside a capture
        self._poses = Poses(w)
        self._wrenches = Wrenches(w)
        self._device_io = DeviceIO(w, self._transfers)
        self._has_commands = bool(self.buffers.command.size)
        self._ctrl_behind = False  # whether the host's ctrl lags the device's kept copy (after apply_commands)

    def close(self) -> None:
        self._graphs.clear()
        for name in ("_worlds", "_transfers", "_period", "_reset", "_poses", "_wrenches", "_device_io"):
            self.__dict__.pop(name, None)

    # --- commands: write() ---
    def ctrl(self) -> np.ndarray:
        if self._ctrl_behind:  # the commands went up whole: bring the kept ctrl down (a reset's, a park's)
            with wp.ScopedDevice(self.device):
                self._transfers.download_ctrl()
                wp.synchronize_device(self.device)
            self._ctrl_behind = False
        return self._transfers.ctrl

    def upload_ctrl(self) -> None:
        self.ctrl()  # up to date first: all of it goes up
        if self._graphs.replay(WRITE):
            return
        with wp.ScopedDevice(self.device):
            self._graphs.run(WRITE, self._transfers.upload)

    def apply_commands(self) -> np.ndarray | None:
        if not self._has_commands:
            return None
        if not self._graphs.replay(COMMANDS):
            with wp.ScopedDevice(self.device):
                self._graphs.run(COMMANDS, self._transfers.commands)
        wp.synchronize_device(self.device)
        self._ctrl_behind = self._cuda  # (the CPU device writes the host's)
        return self._transfers.rejected

    # --- state: read(), step() ---
    def read(self) -> None:
        if not self._graphs.replay(READ):
            with wp.ScopedDevice(self.device):
                self._graphs.run(READ, self._transfers.read)
        wp.synchronize_device(self.device)

    def step(
        self,
        nstep: int,
        meanwhile: Callable[[], None],
        start: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    ) -> StepFailures | None:
        period = self._period
        while True:
            period.launch(nstep, meanwhile)
            codes = period.flags
            if not codes.any():
                return None
            live = (codes != 0) & ~self.buffers.frozen
            if not live.any():
                return None
            if not self._grow(codes, live):
                return self._failures(np.flatnonzero(live), codes)
            # grown, and every world back at the period's start: run the period again

    def _failures(self, worlds: np.ndarray, codes: np.ndarray) -> StepFailures:
        """The failed worlds, read (raw) as they were when the period started."""
        w = self._worlds
        mask = np.zeros(self.nworld, bool)
        mask[worlds] = True
        with wp.ScopedDevice(self.device):
            overflow = w.d.overflow.numpy()[worlds] & BUFFER_OVERFLOWS
            w.mask.assign(mask)
            self._period.restore_start(w.mask)  # they are parked right after: no harm done
            readings, sensordata, time = self._transfers.gather_rows(worlds)
        return StepFailures(
            worlds=worlds,
            status=code_status(codes[worlds]),
            reasons=self._failure_reasons(codes[worlds], lambda i: overflow_reason(int(overflow[i]), self._cannot_grow)),
            readings=readings,
            sensordata=sensordata,
            time=time,
        )

    def _reset_on_device(self, worlds: np.ndarray | None) -> None:
        self._reset(worlds, self.buffers.frozen)

    # --- growing the buffers (batchsim.backends.warp.buffers) ---
    def _grow(self, codes: np.ndarray, live: np.ndarray) -> bool:
        """Grow the buffers that overflowed in this period and restore every world to its start.
        False if nothing that overflowed can grow, or there is not the memory for it."""
        self._cannot_grow = ""
        overflowed = live & ((codes & int(Status.OVERFLOW)) != 0)
        if not overflowed.any():
            return False
        d = self._worlds.d
        bits = int(np.bitwise_or.reduce(d.overflow.numpy()[overflowed] & BUFFER_OVERFLOWS))
        grows = growable(bits)
        if not grows:
            return False
        now = {"nconmax": self.nconmax, "njmax": self.njmax}
        max_bytes = self.options["max_data_bytes"]
        limited_by = "the device's free memory" if max_bytes is None else "max_data_bytes"
        size, self._cannot_grow = plan_growth(
            d, self.nworld, now, grows, memory_for_data(self.device, max_bytes), limited_by
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
        w = self._worlds
        with wp.ScopedDevice(self.device):
            self._period.restore_start(None)
            new = grown_data(w.m, self.model, w.d, self.nworld, nconmax, njmax)
            wp.synchronize_device(self.device)
        w.d = new
        self.nconmax, self.njmax = nconmax, njmax
        self._graphs.clear()  # they launch on the old buffers: capture again
        if self._sensors is not None:
            self._sensors.graphs.clear()  # likewise

    # --- the whole joint state, per-world fields, plugins ---
    def qstate(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = self._worlds.d
        with wp.ScopedDevice(self.device):
            return d.qpos.numpy()[worlds], d.qvel.numpy()[worlds]

    def set_qstate(self, worlds: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        # a rare teleport: whole arrays down and up, written in place (captured graphs keep their pointers)
        d = self._worlds.d
        with wp.ScopedDevice(self.device):
            for array, rows in ((d.qpos, qpos), (d.qvel, qvel)):
                values = array.numpy()
                values[worlds] = rows
                array.assign(values)

    def set_model_fields(self, worlds: np.ndarray, params: dict[str, np.ndarray]) -> None:
        set_world_fields(self._worlds.m, self.nworld, self.device, worlds, params)

    def stage_base_velocity(self, target: np.ndarray) -> None:
        self._period.stage_base_velocity(target)

    def stage_xfrc(self, worlds: np.ndarray, xfrc: np.ndarray) -> None:
        self._wrenches.stage(worlds, xfrc)

    def body_poses(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self._poses.of(worlds)

    def pose_rows(self) -> tuple[np.ndarray, np.ndarray]:
        # every world's, as tf asks each period: float32, no gather, no allocation
        return self._poses.rows()

    # --- cameras and lidars (warp/sensors.py) ---
    def _sensor_helper(self) -> Sensors:
        if self._sensors is None:
            self._sensors = Sensors(self._worlds, self.options["graph"])
        return self._sensors

    def render_frames(self, camera: Camera, worlds: np.ndarray, copy: bool) -> tuple[np.ndarray, np.ndarray]:
        return self._sensor_helper().frames(camera, worlds, copy)

    def device_frames(self, camera: Camera) -> tuple[wp.array, wp.array]:
        return self._sensor_helper().device_frames(camera)

    def cast_ranges(self, lidar: Lidar, worlds: np.ndarray, copy: bool) -> np.ndarray:
        return self._sensor_helper().ranges(lidar, worlds, copy)

    def device_ranges(self, lidar: Lidar, host: Callable[[], np.ndarray]) -> wp.array:
        """Every world's (nworld, nray) float32 REP 117 ranges on the device, overwritten by the next
        scan of this lidar; a rangefinder lidar's are its sensordata's, uploaded."""
        if lidar.kind is LidarKind.RANGEFINDER:
            return wp.array(host(), dtype=wp.float32, device=self.device)
        return self._sensor_helper().cast(lidar)["ranges"]

    def to_device(self, array: np.ndarray) -> wp.array:
        return wp.array(array, device=self.device)

    def close_sensors(self) -> None:
        self._sensors = None

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
        d = self._worlds.d
        return {f: getattr(d, f) for f in DEVICE_ARRAYS}

    def device_state(self, sign: np.ndarray) -> wp.array:
        return self._device_io.state(sign)

    def write_device(self, command: Any) -> None:
        self._device_io.write(command)
        self._ctrl_behind = self._cuda  # the host's ctrl lags the kept copy (the CPU device wrote it)
