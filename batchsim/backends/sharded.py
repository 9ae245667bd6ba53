"""One fleet over several devices: the worlds split into contiguous ranges, one backend
system per device, behind the one contract.

    sim = batchsim.make("humanoid", 16384, "warp", devices=[0, 1])
    sim.state          # (16384, nstate): worlds 0..8191 on cuda:0, 8192..16383 on cuda:1
    sim.world_ranges   # each device's worlds

    sim = batchsim.make("humanoid", 16384, "warp", devices=[0, 1], processes=True)

Each period every shard steps on its own device at once, and step() returns when the
slowest is done, so every world is at the same sim time after each period. A shard is an
ordinary backend system of its device (batchsim/backends/shards.py): it checks its worlds'
commands, freezes its diverged worlds and grows its own buffers. Its shard of the fleet's
arrays (readings, sensordata, time, status, command) is where it reads its commands and
writes its readings; the loop, controllers and bridge see one system and never the devices.

Two ways to run the shards:
- threads (the default): every device's system in this process, one thread each (Warp and
  JAX release the GIL while their devices run). `device_arrays()` and `render(device=True)`
  give each device's own arrays. The shards' host work (checking commands, gathering
  readings) shares this process's GIL.
- processes (`processes=True`, what `batchsim --devices` uses on GPUs): one process per
  device, the fleet's arrays in shared memory (batchsim.memory), so each shard's host work
  runs on its own core; a device's arrays then live in its process, and `device_arrays()`
  and `render(device=True)` give host copies of them. Where there are cores to spare, the
  fleet and its shard processes poll for each other's messages rather than sleep
  (shards.spin_budget): a woken process starts late, four times a period.

Cameras and lidars render and cast on each shard; sensor noise is the fleet's, seeded by
fleet world numbers, so a world's noise does not depend on how many devices there are.
"""

from __future__ import annotations

import dataclasses
import os
import weakref
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from batchsim.backends.fleet_rows import FleetRows, fleet_layout
from batchsim.backends.shards import LocalShard, ProcessShard, ShardOp, spin_budget
from batchsim.hardware import BatchedSystem, CallbackReturn, ConfigurationError, LifecycleState, ReturnType
from batchsim.loop import OptionError
from batchsim.memory import Memory
from batchsim.model import RobotSpec
from batchsim.sensors import Camera, Lidar, SensorConfig
from batchsim.types import check_nstep, split_worlds
from batchsim.variation import Bound
from batchsim.variation import load as load_variation


class PerDevice(Sequence[Any]):
    """One field of a sharded system: its per-device arrays, in world order.

    Index it for one device's array (zero copy); `np.asarray` joins them on the host."""

    def __init__(self, parts: list[Any]):
        self.parts = parts

    def __getitem__(self, i: int) -> Any:  # type: ignore[override]
        return self.parts[i]

    def __len__(self) -> int:
        return len(self.parts)

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        host = [p.numpy() if hasattr(p, "numpy") else np.asarray(p) for p in self.parts]
        return np.concatenate(host).astype(dtype) if dtype is not None else np.concatenate(host)


class ShardedSystem(BatchedSystem):
    """`nworld` worlds of one backend spread over `devices`, one system per device.

    Args:
      backend: the per-device system class (a device backend: warp or mjx).
      spec, nworld: as for any system.
      devices: one device per shard, as that backend's `device` option takes it.
      processes: run each shard in a process of its own (see the module's docstring).
      pin: with processes, run each shard process on cores of its own, an equal share of
        this process's (benchmarks/devices.py compares it).
      **options: the backend's options, given to every shard.

    Attributes:
      shards: one handle per device, in world order: a LocalShard (its `.system` is that
        device's backend system) or a ProcessShard (its `.pid`).
      world_ranges: the worlds of each shard.
      devices: the device of each shard.
      processes: whether the shards run in processes of their own.
    """

    OPTIONS: ClassVar[dict[str, Any]] = {}
    drives_base = False  # the BaseVelocityPlugin's commands do not reach the shards: refused, named
    _sharded_variation: Any = None
    applies_wrenches = False  # nor do external wrenches

    def __init__(
        self,
        backend: type[BatchedSystem],
        spec: RobotSpec,
        nworld: int,
        devices: Sequence[Any],
        *,
        processes: bool = False,
        pin: bool = False,
        **options: Any,
    ):
        super().__init__(spec, nworld)
        if "device" not in backend.OPTIONS:
            raise OptionError("", f"the {backend.name} backend does not run on devices; it cannot be sharded")
        self.name = backend.name
        self.compiles_first_period = backend.compiles_first_period  # type: ignore[misc]
        self.devices = list(devices)
        self.processes = bool(processes)
        if not 1 <= len(self.devices) <= self.nworld:
            raise OptionError("", f"{self.nworld} worlds cannot be split over {len(self.devices)} devices")
        backend.check_options(options)  # once, here, before any shard (a process's error would come back late)
        self.world_ranges = split_worlds(self.nworld, len(self.devices))
        self.sensors_batched = backend.sensors_batched
        self.reads_torque_sensors = backend.reads_torque_sensors  # type: ignore[misc]
        # the fleet's arrays, in one block that every shard reads its commands from and
        # writes its readings to (shared memory when the shards are processes)
        ncolumn, nbody = self._readings.shape[1], self.model.nbody
        layout = fleet_layout(
            self.nworld, ncolumn, self.model.nsensordata, len(spec.commands), nbody, len(self.devices)
        )
        self.memory = Memory.create(layout, shared=self.processes)
        self.memory["command"][:] = self._command
        self._bind_readings(self.memory["readings"])
        self._bind_sensordata(self.memory["sensordata"])
        self.time, self.status, self._command = (
            self.memory["time"],
            self.memory["status"],
            self.memory["command"],
        )
        rows = [FleetRows(self.memory, r) for r in self.world_ranges]
        self._pool: ThreadPoolExecutor | None = None
        self.shards: list[LocalShard | ProcessShard] = []
        if self.processes:
            spin = spin_budget(len(self.devices))
            cpus = _share_cores(len(self.devices)) if pin else [None] * len(self.devices)
            try:
                for slot, (r, device, mine) in enumerate(zip(self.world_ranges, self.devices, cpus, strict=True)):
                    self.shards.append(
                        ProcessShard(backend.name, spec, r, device, options, self.memory, self.nworld, spin, mine, slot)
                    )
                for shard in self.shards:  # they start at once: wait for each
                    shard.started()
            except BaseException:
                _close(self.shards, self.memory)
                raise
        else:
            self._pool = ThreadPoolExecutor(len(self.devices), thread_name_prefix="batchsim-shard")
            for r, device, fleet_rows in zip(self.world_ranges, self.devices, rows, strict=True):
                system = backend(spec, len(r), **{**options, "device": device})
                system.number_worlds_as(r.start, self.nworld)  # failure lines name fleet worlds
                fleet_rows.share(system)
                self.shards.append(LocalShard(system, fleet_rows, self._pool))
        self.options = dict(self.shards[0].options, device=self.devices)
        self._stepped: set[int] = set()  # period lengths every shard has compiled or captured
        # tf's poses of every world: asked for since the last read (the next read brings them along),
        # and whether the fleet's pose rows are the engine's current ones (no shard op changed them since)
        self._poses_wanted = self._poses_current = False
        # a fleet dropped without shutdown() still stops its shard processes and frees its memory
        self._finalizer = weakref.finalize(self, _close, list(self.shards), self.memory, self._pool)

    def __repr__(self) -> str:
        how = "processes" if self.processes else "threads"
        return f"ShardedSystem({self.name}, {self.nworld} worlds on {self.devices}, {how})"

    # --- lifecycle: every shard follows the fleet ---
    def on_init(self) -> CallbackReturn:
        self._each(ShardOp.INITIALIZE, parallel=self.processes)
        return CallbackReturn.SUCCESS

    def on_configure(self, previous_state: LifecycleState) -> CallbackReturn:
        # the first shard alone: it compiles the kernels the others then load from the cache
        # (and in one process, loading kernels and models is not thread-safe)
        self._poses_current = False
        self.shards[0].call(ShardOp.CONFIGURE)
        self._each(ShardOp.CONFIGURE, shards=self.shards[1:], parallel=self.processes)
        return CallbackReturn.SUCCESS

    def on_activate(self, previous_state: LifecycleState) -> CallbackReturn:
        self._each(ShardOp.ACTIVATE, parallel=self.processes)
        return CallbackReturn.SUCCESS

    def on_deactivate(self, previous_state: LifecycleState) -> CallbackReturn:
        self._each(ShardOp.DEACTIVATE, parallel=self.processes)
        return CallbackReturn.SUCCESS

    def on_cleanup(self, previous_state: LifecycleState) -> CallbackReturn:
        self._each(ShardOp.CLEANUP, parallel=self.processes)
        return CallbackReturn.SUCCESS

    def on_shutdown(self, previous_state: LifecycleState) -> CallbackReturn:
        live = [s for s in self.shards if s.lifecycle_state is not LifecycleState.FINALIZED]
        try:
            self._each(ShardOp.SHUTDOWN, shards=live, parallel=self.processes)
        finally:
            self._finalizer()
        return CallbackReturn.SUCCESS

    def on_error(self, previous_state: LifecycleState) -> CallbackReturn:
        live = [
            s
            for s in self.shards
            if s.lifecycle_state not in (LifecycleState.UNKNOWN, LifecycleState.FINALIZED)
        ]
        self._each(ShardOp.ERROR, shards=live, parallel=False)
        return CallbackReturn.SUCCESS

    # --- the contract, over the shards ---
    def read(self, time: float | None = None, period: float | None = None) -> ReturnType:
        if self.lifecycle_state not in (LifecycleState.INACTIVE, LifecycleState.ACTIVE):
            return ReturnType.OK
        # every device's download at once; each shard writes its rows of the fleet's arrays, and
        # its body poses where tf asked for them last period (no round trip of their own then)
        with_poses, self._poses_wanted = self._poses_wanted, False
        self._each(ShardOp.READ_POSES if with_poses else ShardOp.READ, time, period)
        self._poses_current = with_poses
        self._add_noise()  # frozen worlds keep their held, noise-free readings
        return ReturnType.OK

    def write(self, time: float | None = None, period: float | None = None) -> ReturnType:
        if self.lifecycle_state is not LifecycleState.ACTIVE:
            return ReturnType.OK
        self._each(ShardOp.WRITE, time, period)  # each shard takes its rows of `command`; uploads at once
        return ReturnType.OK

    steps_on_device = True  # the shards step; `meanwhile` runs once every one has its request

    def step(self, nstep: int = 1, meanwhile: Callable[[], None] | None = None) -> None:
        """Advance every world `nstep` steps, every device at once; returns when all are done.
        `meanwhile` as BatchedSystem.step's: here, once every shard has the request."""
        self._require("step", frozenset({LifecycleState.INACTIVE, LifecycleState.ACTIVE}))
        check_nstep(nstep)
        # the first period of a length compiles or captures it: one device at a time
        parallel = nstep in self._stepped
        self._meanwhile, self._meanwhile_error = meanwhile, None  # as BatchedSystem.step: raised once done
        if not parallel:
            self._while_stepping()
        try:
            self._each(ShardOp.STEP, int(nstep), parallel=parallel, meanwhile=self._while_stepping)
        finally:
            self._meanwhile = None
        self._stepped.add(nstep)
        self._raise_meanwhile_error()

    def reset(self, worlds: Sequence[int] | np.ndarray | None = None) -> None:
        """Reset all or the listed worlds (fleet numbering), each on its shard."""
        self._require(
            "reset", frozenset({LifecycleState.UNCONFIGURED, LifecycleState.INACTIVE, LifecycleState.ACTIVE})
        )
        rows = self._worlds(worlds)
        calls = []
        for shard, r in zip(self.shards, self.world_ranges, strict=True):
            local = None if rows is None else rows[(rows >= r.start) & (rows < r.stop)] - r.start
            # reset refreshes every world's readings, as on one device
            calls.append((shard, ShardOp.RESET, (local,)) if local is None or local.size else (shard, ShardOp.READ, ()))
        self._run(calls, self.processes)
        self._add_noise()  # frozen worlds keep their held, noise-free readings

    # --- per-world randomization: each shard draws its own worlds, as world_ranges number them ---
    def set_variation(self, variation: Any, first_world: int = 0) -> None:
        """As BatchedSystem.set_variation: every shard draws its worlds as the fleet's
        `first_world + world_ranges[i].start + j`, so a world draws the same however it is split."""
        parsed = None if variation is None else load_variation(variation)
        super().set_variation(None)  # the lifecycle check; the shards hold the draws
        self._poses_current = False
        for shard, r in zip(self.shards, self.world_ranges, strict=True):
            shard.call(ShardOp.SET_VARIATION, parsed, int(first_world) + r.start)
        self._sharded_variation = parsed if parsed is not None and parsed.active else None

    @property
    def variation(self) -> Any:
        return self._sharded_variation

    @property
    def variation_bound(self) -> Bound | None:
        variation = self._sharded_variation
        return None if variation is None else Bound(variation, self.model)

    def draw_numbers(self) -> np.ndarray:
        return np.concatenate(self._each(ShardOp.DRAW_NUMBERS))

    def reseed(self, seed: int) -> None:
        self._each(ShardOp.RESEED, seed)

    # --- the device path: each shard's arrays live on its own device ---
    def _device_state(self) -> Any:
        raise ConfigurationError("a fleet over several devices has no one device array: use read() and state")

    def _write_device(self, command: Any) -> None:
        raise ConfigurationError("a fleet over several devices has no one device array: use command and write()")

    def world_params(self, worlds: Sequence[int] | np.ndarray | None = None) -> dict[str, np.ndarray]:
        parts = self._each(ShardOp.WORLD_PARAMS)
        if not parts or not parts[0]:
            return {}
        every = {f: np.concatenate([p[f] for p in parts]) for f in parts[0]}
        rows = self._worlds(worlds)
        return every if rows is None else {f: v[rows] for f, v in every.items()}

    def perform_command_mode_switch(self, start: Sequence[str], stop: Sequence[str] = ()) -> None:
        super().perform_command_mode_switch(start, stop)  # checks the names
        self._each(ShardOp.PERFORM_COMMAND_MODE_SWITCH, list(start), list(stop), parallel=self.processes)

    def device_arrays(self) -> dict[str, PerDevice]:
        """The live device arrays of every shard (see the backend's device_arrays), field by
        field: `arrays["qpos"][i]` is device i's (its worlds are `world_ranges[i]`), zero copy;
        `np.asarray(arrays["qpos"])` copies the whole fleet's to the host. With processes,
        each device's arrays live in its shard process: these are host copies of them,
        taken now (writing them changes nothing)."""
        if self.processes:
            parts = self._each(ShardOp.DEVICE_ARRAYS)
        else:
            parts = [shard.system.device_arrays() for shard in self.shards]  # type: ignore[union-attr]
        return {field: PerDevice([p[field] for p in parts]) for field in parts[0]}

    # --- cameras, lidars, noise: rendered on the shards, noise added by the fleet ---
    def set_sensor_config(self, config: SensorConfig | str | Path | Mapping[str, Any]) -> None:
        super().set_sensor_config(config)
        quiet = dataclasses.replace(self._sensor_config, noise={})  # the fleet adds the noise
        self._each(ShardOp.SET_SENSOR_CONFIG, quiet, parallel=self.processes)

    def _render_frames(self, camera: Camera, worlds: np.ndarray, copy: bool) -> tuple[np.ndarray, np.ndarray]:
        # the shards' parts concatenated: arrays of the caller's own whatever `copy` says
        parts = self._run(
            [(s, ShardOp.RENDER, (camera.name, local)) for s, local in self._split(worlds)], self.processes
        )
        return np.concatenate([p.rgb for p in parts]), np.concatenate([p.depth for p in parts])

    def _device_frames(self, camera: Camera) -> tuple[PerDevice, PerDevice]:
        if self.processes:  # host copies, from each shard process (see device_arrays)
            parts = self._each(ShardOp.DEVICE_FRAMES, camera.name)
        else:
            parts = [shard.system.render(camera.name, device=True) for shard in self.shards]  # type: ignore[union-attr]
        return PerDevice([p.rgb for p in parts]), PerDevice([p.depth for p in parts])

    def _cast_ranges(self, lidar: Lidar, worlds: np.ndarray, copy: bool) -> np.ndarray:
        calls = [(s, ShardOp.SCAN, (lidar.name, local)) for s, local in self._split(worlds)]
        return np.concatenate(self._run(calls, self.processes))

    def _device_ranges(self, lidar: Lidar) -> PerDevice:
        if self.processes:  # host copies, from each shard process (see device_arrays)
            return PerDevice(self._each(ShardOp.DEVICE_RANGES, lidar.name))
        return PerDevice([shard.system.scan(lidar.name, device=True) for shard in self.shards])  # type: ignore[union-attr]

    _pose_rows_hold_frozen = True  # each shard's body_poses() shows its frozen worlds' held poses

    def _pose_rows(self) -> tuple[np.ndarray, np.ndarray]:
        # every world, as tf asks each period: in the fleet's rows, nothing pickled nor copied here;
        # brought by this period's read where tf asked last period too, else fetched now
        self._poses_wanted = True
        if not self._poses_current:
            self._each(ShardOp.POSES)
            self._poses_current = True
        return self.memory["xpos"], self.memory["xquat"]

    def _body_poses(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # each shard's worlds in ascending order, then put back in the order asked for
        order = np.argsort(worlds, kind="stable")
        parts = self._run([(s, ShardOp.BODY_POSES, (local,)) for s, local in self._split(worlds[order])], self.processes)
        xpos, xquat = np.empty((len(worlds), self.model.nbody, 3)), np.empty((len(worlds), self.model.nbody, 4))
        if parts:
            xpos[order], xquat[order] = np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
        return xpos, xquat

    def _qstate(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        order = np.argsort(worlds, kind="stable")
        parts = self._run([(s, ShardOp.QSTATE, (local,)) for s, local in self._split(worlds[order])], self.processes)
        qpos, qvel = np.empty((len(worlds), self.model.nq)), np.empty((len(worlds), self.model.nv))
        if parts:
            qpos[order], qvel[order] = np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
        return qpos, qvel

    def _refresh(self) -> None:
        self._each(ShardOp.READ, None, None)  # each shard writes its rows of the fleet's arrays

    def _set_qstate(self, worlds: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        order = np.argsort(worlds, kind="stable")
        qpos, qvel = qpos[order], qvel[order]
        calls, at = [], 0
        for s, local in self._split(worlds[order]):
            calls.append((s, ShardOp.SET_QSTATE, (local, qpos[at : at + len(local)], qvel[at : at + len(local)])))
            at += len(local)
        self._run(calls, self.processes)

    def _split(self, worlds: np.ndarray) -> list[tuple[LocalShard | ProcessShard, np.ndarray]]:
        """(shard, its local world indices) for the fleet's `worlds`, ascending, in shard order."""
        out = []
        for shard, r in zip(self.shards, self.world_ranges, strict=True):
            local = worlds[(worlds >= r.start) & (worlds < r.stop)] - r.start
            if local.size:
                out.append((shard, local))
        return out

    # --- helpers ---
    def _each(
        self,
        op: ShardOp,
        *args: Any,
        shards: Sequence[LocalShard | ProcessShard] | None = None,
        parallel: bool = True,
        meanwhile: Callable[[], None] | None = None,
    ) -> list[Any]:
        """`op(*args)` on every shard (or those given): at once, or one after the other."""
        shards = self.shards if shards is None else shards
        return self._run([(shard, op, args) for shard in shards], parallel, meanwhile)

    def _run(
        self, calls: list[tuple[Any, ShardOp, tuple]], parallel: bool, meanwhile: Callable[[], None] | None = None
    ) -> list[Any]:
        """Run (shard, op, args) calls, at once or in turn; their results in order. Every
        call is answered before the first failure is raised (a shard process then still
        takes requests). `meanwhile()` (which must not raise) runs once every call is submitted
        (parallel only)."""
        if any(op not in _KEEP_POSES for _, op, _ in calls):
            self._poses_current = False  # a step, a reset, a lifecycle call: the poses are the engine's to give again
        if not parallel:
            return [shard.call(op, *args) for shard, op, args in calls]
        pending, failure = [], None
        for shard, op, args in calls:
            try:
                pending.append(shard.submit(op, *args))
            except Exception as e:  # a shard process that has exited: the others still answer
                pending.append(None)
                failure = failure or e
        if meanwhile is not None:
            meanwhile()
        results = []
        for p in pending:
            try:
                results.append(None if p is None else p.result())
            except BaseException as e:
                results.append(None)
                failure = failure or e
        if failure is not None:
            raise failure
        return results


# the operations after which the fleet's pose rows still hold the engine's current poses
_KEEP_POSES = frozenset(
    {ShardOp.WRITE, ShardOp.READ, ShardOp.BODY_POSES, ShardOp.QSTATE, ShardOp.WORLD_PARAMS, ShardOp.DRAW_NUMBERS}
)


def _share_cores(nshard: int) -> list[set[int] | None]:
    """Each of `nshard` shard processes its own cores: this process's cores split into
    nshard + 1 equal groups, the first left to this process and the rest; None where too few."""
    cores = sorted(os.sched_getaffinity(0))
    size = len(cores) // (nshard + 1)
    if size < 1:
        return [None] * nshard
    return [set(cores[(i + 1) * size : (i + 2) * size]) for i in range(nshard)]


def _close(
    shards: Sequence[LocalShard | ProcessShard], memory: Memory, pool: ThreadPoolExecutor | None = None
) -> None:
    """Stop the shard processes, free the fleet's memory and threads (shutdown, or the fleet's end)."""
    for shard in shards:
        shard.close()
    memory.close()
    if pool is not None:
        pool.shutdown(wait=False)
