"""One fleet over several devices: the worlds split into contiguous ranges, one backend
system per device, behind the one contract.

    sim = batchsim.make("humanoid", 16384, "warp", devices=[0, 1])
    sim.state          # (16384, nstate): worlds 0..8191 on cuda:0, 8192..16383 on cuda:1
    sim.world_ranges   # each device's worlds

    sim = batchsim.make("humanoid", 16384, "warp", devices=[0, 1], processes=True)

Each period every shard steps on its own device at once, and step() returns when the
slowest is done, so every world is at the same sim time after each period. A shard is an
ordinary BatchedSystem of its device (batchsim/backends/sharded/shards.py), built by the fleet's
`build`: it checks its worlds' commands, freezes its diverged worlds and grows its own buffers.
The fleet is a composite over them that implements the contract (batchsim.contract.Contract):
what a user sees over its parts (batchsim.parts.face) is the one face every system shares; what
goes to the engine on one device goes to the shards here. Its shard of the fleet's
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
from typing import Any

import numpy as np

from batchsim.backends.sharded.rows import FleetRows, fleet_layout
from batchsim.backends.sharded.shards import LocalShard, ProcessShard, ShardOp, spin_budget
from batchsim.backends.sharded.sources import PerDevice, ShardSources
from batchsim.contract import Contract
from batchsim.engine import Engine, Meanwhile
from batchsim.lifecycle import CallbackReturn, LifecycleState
from batchsim.memory import Memory
from batchsim.model import RobotSpec
from batchsim.parts.actuation import Actuation
from batchsim.parts.face import RUNNING, FaceParts, SystemFace
from batchsim.parts.poses import BodyPoses
from batchsim.parts.readings import Readings
from batchsim.parts.sensing import Sensing
from batchsim.plugins import BaseDrive, Wrenches
from batchsim.sensors import SensorConfig
from batchsim.types import (
    ConfigurationError,
    OptionError,
    ReturnType,
    check_nstep,
    split_worlds,
    worlds_index,
)
from batchsim.variation import Bound
from batchsim.variation import load as load_variation


class ShardedSystem(SystemFace):
    """`nworld` worlds of one engine spread over `devices`, one BatchedSystem per device.

    Args:
      engine: the per-device engine class (a device backend: warp or mjx).
      build: `build(spec, nworld, engine, **options)`, a shard's system (batchsim.build); a shard
        process imports it by its module and name.
      spec, nworld: as for any system.
      devices: one device per shard, as that engine's `device` option takes it.
      processes: run each shard in a process of its own (see the module's docstring).
      pin: with processes, run each shard process on cores of its own, an equal share of
        this process's (benchmarks/devices.py compares it).
      **options: the engine's options, given to every shard.

    Attributes:
      shards: one handle per device, in world order: a LocalShard (its `.system` is that
        device's BatchedSystem) or a ProcessShard (its `.pid`).
      world_ranges: the worlds of each shard.
      devices: the device of each shard.
      processes: whether the shards run in processes of their own.
      memory: the fleet's arrays (batchsim/backends/sharded/rows.py), shared with the shards.
    """

    steps_on_device = True  # the shards step; `meanwhile` runs once every one has its request
    logs_failures = False

    def __init__(
        self,
        engine: type[Engine],
        build: Callable[..., Contract],
        spec: RobotSpec,
        nworld: int,
        devices: Sequence[Any],
        *,
        processes: bool = False,
        pin: bool = False,
        **options: Any,
    ):
        super().__init__(spec, nworld)
        if "device" not in engine.OPTIONS:
            raise OptionError("", f"the {engine.name} backend does not run on devices; it cannot be sharded")
        self.name = engine.name
        for capability in ("compiles_first_period", "sensors_batched", "reads_torque_sensors", "device_dtype"):
            setattr(self, capability, getattr(engine, capability))
        self.devices = list(devices)
        self.processes = bool(processes)
        if not 1 <= len(self.devices) <= self.nworld:
            raise OptionError("", f"{self.nworld} worlds cannot be split over {len(self.devices)} devices")
        engine.check_options(options)  # once, here, before any shard (a process's error would come back late)
        self.world_ranges = split_worlds(self.nworld, len(self.devices))
        actuation = Actuation(spec, self.nworld)  # the command interfaces' names, for mode switches
        readings = Readings(spec, self.nworld, actuation.feedback_columns)
        # the fleet's arrays, in one block that every shard reads its commands from and
        # writes its readings to (shared memory when the shards are processes)
        layout = fleet_layout(
            self.nworld, len(readings.columns), self.model.nsensordata, len(spec.commands), self.model.nbody,
            len(self.devices),
        )  # fmt: skip
        self.memory = Memory.create(layout, shared=self.processes)
        readings.bind(self.memory["readings"], self.memory["sensordata"], self.memory["time"])
        self.status, self._command = self.memory["status"], self.memory["command"]
        frozen = lambda: self.frozen  # noqa: E731  (the parts ask the fleet, whose status changes)
        self.sources = sources = ShardSources(self)
        self.parts = FaceParts(  # its readings are the shards' (finished there), its plugins refuse
            readings=readings,
            actuation=actuation,
            sensing=Sensing(spec, self.nworld, readings, sources, frozen),
            poses=BodyPoses(spec, self.nworld, sources, frozen, hold_frozen=True),
            base_drive=BaseDrive(self.model, self.nworld, _refused, runs=False),
            wrenches=Wrenches(self.model, self.nworld, _refused, self.body_poses, runs=False),
        )
        rows = [FleetRows(self.memory, r) for r in self.world_ranges]
        self._pool: ThreadPoolExecutor | None = None
        self.shards: list[LocalShard | ProcessShard] = []
        if self.processes:
            spin = spin_budget(len(self.devices))
            cpus = _share_cores(len(self.devices)) if pin else [None] * len(self.devices)
            by_name = f"{build.__module__}:{build.__qualname__}"
            try:
                for slot, (r, device, mine) in enumerate(zip(self.world_ranges, self.devices, cpus, strict=True)):
                    self.shards.append(
                        ProcessShard(by_name, engine.name, spec, r, device, options, self.memory, self.nworld, spin, mine, slot)
                    )
                for shard in self.shards:  # they start at once: wait for each
                    shard.started()
            except BaseException:
                _close(self.shards, self.memory)
                raise
        else:
            self._pool = ThreadPoolExecutor(len(self.devices), thread_name_prefix="batchsim-shard")
            for r, device, fleet_rows in zip(self.world_ranges, self.devices, rows, strict=True):
                system = build(spec, len(r), engine, **{**options, "device": device})
                system.number_worlds_as(r.start, self.nworld)  # failure lines name fleet worlds
                fleet_rows.share(system)
                self.shards.append(LocalShard(system, fleet_rows, self._pool))
        self.options = dict(self.shards[0].options, device=self.devices)
        self._stepped: set[int] = set()  # period lengths every shard has compiled or captured
        self._variation: Any = None

        # a fleet dropped without shutdown() still stops its shard processes and frees its memory
        self._finalizer = weakref.finalize(self, _close, list(self.shards), self.memory, self._pool)

    def __repr__(self) -> str:
        how = "processes" if self.processes else "threads"
        return f"ShardedSystem({self.name}, {self.nworld} worlds on {self.devices}, {how})"

    # --- lifecycle: every shard follows the fleet ---
    def on_init(self) -> CallbackReturn:
        self.each(ShardOp.INITIALIZE, parallel=self.processes)
        return CallbackReturn.SUCCESS

    def on_configure(self, previous_state: LifecycleState) -> CallbackReturn:
        # the first shard alone: it compiles the kernels the others then load from the cache
        # (and in one process, loading kernels and models is not thread-safe)
        self.sources.poses_current = False
        self.shards[0].call(ShardOp.CONFIGURE)
        self.each(ShardOp.CONFIGURE, shards=self.shards[1:], parallel=self.processes)
        self.parts.readings.current = True
        return CallbackReturn.SUCCESS

    def on_activate(self, previous_state: LifecycleState) -> CallbackReturn:
        self.each(ShardOp.ACTIVATE, parallel=self.processes)
        return CallbackReturn.SUCCESS

    def on_deactivate(self, previous_state: LifecycleState) -> CallbackReturn:
        self.each(ShardOp.DEACTIVATE, parallel=self.processes)
        return CallbackReturn.SUCCESS

    def on_cleanup(self, previous_state: LifecycleState) -> CallbackReturn:
        self.each(ShardOp.CLEANUP, parallel=self.processes)
        return CallbackReturn.SUCCESS

    def on_shutdown(self, previous_state: LifecycleState) -> CallbackReturn:
        live = [s for s in self.shards if s.lifecycle_state is not LifecycleState.FINALIZED]
        try:
            self.each(ShardOp.SHUTDOWN, shards=live, parallel=self.processes)
        finally:
            self._finalizer()
        return CallbackReturn.SUCCESS

    def on_error(self, previous_state: LifecycleState) -> CallbackReturn:
        live = [
            s
            for s in self.shards
            if s.lifecycle_state not in (LifecycleState.UNKNOWN, LifecycleState.FINALIZED)
        ]
        self.each(ShardOp.ERROR, shards=live, parallel=False)
        return CallbackReturn.SUCCESS

    # --- the contract, over the shards ---
    def read(self, time: float | None = None, period: float | None = None) -> ReturnType:
        """As BatchedSystem.read: every shard reads its worlds into the fleet's rows at once."""
        if self.lifecycle_state not in RUNNING:
            return ReturnType.OK
        # every device's download at once; each shard writes its rows of the fleet's arrays, and
        # its body poses where tf asked for them last period (no round trip of their own then)
        with_poses, self.sources.poses_wanted = self.sources.poses_wanted, False
        self.each(ShardOp.READ_POSES if with_poses else ShardOp.READ, time, period)
        self.sources.poses_current = with_poses
        self.parts.sensing.add_noise()  # frozen worlds keep their held, noise-free readings
        return ReturnType.OK

    def write(self, time: float | None = None, period: float | None = None) -> ReturnType:
        """As BatchedSystem.write: each shard takes its rows of `command` and uploads at once."""
        if self.lifecycle_state is not LifecycleState.ACTIVE:
            return ReturnType.OK
        self.each(ShardOp.WRITE, time, period)
        return ReturnType.OK

    def step(self, nstep: int = 1, meanwhile: Callable[[], None] | None = None) -> None:
        """Advance every world `nstep` steps, every device at once; returns when all are done.
        `meanwhile` as BatchedSystem.step's: here, once every shard has the request."""
        self._require("step", RUNNING)
        check_nstep(nstep)
        # the first period of a length compiles or captures it: one device at a time
        parallel = nstep in self._stepped
        once = Meanwhile(meanwhile)  # as BatchedSystem.step: what it raises is raised once done
        if not parallel:
            once()
        self.each(ShardOp.STEP, int(nstep), parallel=parallel, meanwhile=once)
        self._stepped.add(nstep)
        if once.error is not None:
            raise once.error

    def reset(self, worlds: Sequence[int] | np.ndarray | None = None) -> None:
        """Reset all or the listed worlds (fleet numbering), each on its shard."""
        self._require("reset", frozenset({LifecycleState.UNCONFIGURED, *RUNNING}))
        rows = worlds_index(worlds, self.nworld)
        calls = []
        for shard, r in zip(self.shards, self.world_ranges, strict=True):
            local = None if rows is None else rows[(rows >= r.start) & (rows < r.stop)] - r.start
            # reset refreshes every world's readings, as on one device
            calls.append((shard, ShardOp.RESET, (local,)) if local is None or local.size else (shard, ShardOp.READ, ()))
        self.run(calls, self.processes)
        self.parts.sensing.add_noise()  # frozen worlds keep their held, noise-free readings

    def perform_command_mode_switch(self, start: Sequence[str], stop: Sequence[str] = ()) -> None:
        """As BatchedSystem's, on every shard (the names checked here first)."""
        self.parts.actuation.switch(start, stop)
        self.each(ShardOp.PERFORM_COMMAND_MODE_SWITCH, list(start), list(stop), parallel=self.processes)

    def set_sensor_config(self, config: SensorConfig | str | Path | Mapping[str, Any]) -> None:
        """As BatchedSystem's; the shards render and cast, the fleet adds the noise."""
        super().set_sensor_config(config)
        quiet = dataclasses.replace(self.parts.sensing.config, noise={})
        self.each(ShardOp.SET_SENSOR_CONFIG, quiet, parallel=self.processes)

    # --- the whole joint state: each world's on its shard ---
    def qstate(self, worlds: Sequence[int] | np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """As BatchedSystem.qstate (the fleet's world numbers)."""
        self._require("read the joint state", RUNNING)
        rows = worlds_index(worlds, self.nworld)
        sel = np.arange(self.nworld) if rows is None else rows
        qpos, qvel = (np.empty((len(sel), n)) for n in (self.model.nq, self.model.nv))
        order = np.argsort(sel, kind="stable")
        parts = self.run([(s, ShardOp.QSTATE, (local,)) for s, local in self.split(sel[order])], self.processes)
        if parts:
            qpos[order], qvel[order] = np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
        return qpos, qvel

    def physics_state(self, worlds: Sequence[int] | np.ndarray | None) -> np.ndarray:
        """Not on a fleet over several devices: re-simulation (batchsim.resim) records one device's."""
        raise NotImplementedError("a fleet over several devices does not record its physics state: use one device")

    def physics_inputs(self, worlds: Sequence[int] | np.ndarray | None) -> dict[str, np.ndarray]:
        """Not on a fleet over several devices (physics_state)."""
        raise NotImplementedError("a fleet over several devices does not record its physics inputs: use one device")

    def set_physics_state(self, worlds: Sequence[int] | np.ndarray | None, states: Any) -> None:
        """Not on a fleet over several devices (physics_state)."""
        raise NotImplementedError("a fleet over several devices does not take a whole physics state: use one device")

    def set_world_params(self, worlds: Sequence[int] | np.ndarray | None, params: Any) -> None:
        """Not on a fleet over several devices (physics_state)."""
        raise NotImplementedError("a fleet over several devices does not take model values per world: use one device")

    def set_qstate(self, worlds: Sequence[int] | np.ndarray | None, qpos: Any, qvel: Any) -> None:
        """As BatchedSystem.set_qstate (the fleet's world numbers)."""
        self._require("write the joint state", RUNNING)
        sel, qpos, qvel = self._checked_qstate(worlds, qpos, qvel)
        order = np.argsort(sel, kind="stable")
        qpos, qvel = qpos[order], qvel[order]
        calls, at = [], 0
        for s, local in self.split(sel[order]):
            calls.append((s, ShardOp.SET_QSTATE, (local, qpos[at : at + len(local)], qvel[at : at + len(local)])))
            at += len(local)
        self.run(calls, self.processes)
        self.each(ShardOp.READ, None, None)  # each shard writes its rows of the fleet's arrays
        self.parts.sensing.add_noise()

    # --- per-world randomization: each shard draws its own worlds, as world_ranges number them ---
    def set_variation(self, variation: Any, first_world: int = 0) -> None:
        """As BatchedSystem.set_variation: every shard draws its worlds as the fleet's
        `first_world + world_ranges[i].start + j`, so a world draws the same however it is split."""
        if self.lifecycle_state is not LifecycleState.UNCONFIGURED:
            from batchsim.lifecycle import LifecycleError

            raise LifecycleError("set the variation before configure(): the worlds draw when they are allocated")
        parsed = None if variation is None else load_variation(variation)
        self.sources.poses_current = False
        for shard, r in zip(self.shards, self.world_ranges, strict=True):
            shard.call(ShardOp.SET_VARIATION, parsed, int(first_world) + r.start)
        self._variation = parsed if parsed is not None and parsed.active else None

    @property
    def variation(self) -> Any:
        return self._variation

    @property
    def variation_bound(self) -> Bound | None:
        return None if self._variation is None else Bound(self._variation, self.model)

    def world_params(self, worlds: Sequence[int] | np.ndarray | None = None) -> dict[str, np.ndarray]:
        parts = self.each(ShardOp.WORLD_PARAMS)
        if not parts or not parts[0]:
            return {}
        every = {f: np.concatenate([p[f] for p in parts]) for f in parts[0]}
        rows = worlds_index(worlds, self.nworld)
        return every if rows is None else {f: v[rows] for f, v in every.items()}

    def draw_numbers(self) -> np.ndarray:
        return np.concatenate(self.each(ShardOp.DRAW_NUMBERS))

    def reseed(self, seed: int) -> None:
        self.each(ShardOp.RESEED, seed)

    # --- the device path: each shard's arrays live on its own device ---
    def device_arrays(self) -> dict[str, PerDevice]:
        """The live device arrays of every shard (see the engine's device_arrays), field by
        field: `arrays["qpos"][i]` is device i's (its worlds are `world_ranges[i]`), zero copy;
        `np.asarray(arrays["qpos"])` copies the whole fleet's to the host. With processes,
        each device's arrays live in its shard process: these are host copies of them,
        taken now (writing them changes nothing)."""
        if self.processes:
            parts = self.each(ShardOp.DEVICE_ARRAYS)
        else:
            parts = [shard.system.device_arrays() for shard in self.shards]  # type: ignore[union-attr]
        return {field: PerDevice([p[field] for p in parts]) for field in parts[0]}

    def device_state(self) -> Any:
        raise ConfigurationError("a fleet over several devices has no one device array: use read() and state")

    def write_device(self, command: Any) -> None:
        raise ConfigurationError("a fleet over several devices has no one device array: use command and write()")

    # --- the shards, asked ---
    def split(self, worlds: np.ndarray) -> list[tuple[LocalShard | ProcessShard, np.ndarray]]:
        """(shard, its local world indices) for the fleet's `worlds`, ascending, in shard order."""
        out = []
        for shard, r in zip(self.shards, self.world_ranges, strict=True):
            local = worlds[(worlds >= r.start) & (worlds < r.stop)] - r.start
            if local.size:
                out.append((shard, local))
        return out

    def each(
        self,
        op: ShardOp,
        *args: Any,
        shards: Sequence[LocalShard | ProcessShard] | None = None,
        parallel: bool = True,
        meanwhile: Callable[[], None] | None = None,
    ) -> list[Any]:
        """`op(*args)` on every shard (or those given): at once, or one after the other."""
        shards = self.shards if shards is None else shards
        return self.run([(shard, op, args) for shard in shards], parallel, meanwhile)

    def run(
        self, calls: list[tuple[Any, ShardOp, tuple]], parallel: bool, meanwhile: Callable[[], None] | None = None
    ) -> list[Any]:
        """Run (shard, op, args) calls, at once or in turn; their results in order. Every
        call is answered before the first failure is raised (a shard process then still
        takes requests). `meanwhile()` (which must not raise) runs once every call is submitted
        (parallel only)."""
        if any(op not in _KEEP_POSES for _, op, _ in calls):
            self.sources.poses_current = False  # a step, a reset, a lifecycle call: the poses are the engine's to give again
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


def _refused(*args: Any) -> None:
    """The plugins' staging on a fleet over devices, which refuses them at configuration."""
    raise ConfigurationError("mujoco_ros2_control's plugins do not run on a fleet spread over several devices")


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
