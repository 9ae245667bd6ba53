"""One fleet over several devices: the worlds split into contiguous ranges, one backend
system per device, behind the one contract.

    sim = batchsim.make("humanoid", 16384, "warp", devices=[0, 1])
    sim.state          # (16384, nstate): worlds 0..8191 on cuda:0, 8192..16383 on cuda:1
    sim.shards         # the per-device systems, sim.world_ranges their worlds

Each period every shard steps on its own device at once (one host thread per shard: Warp
and JAX release the GIL while their devices run, so the devices overlap), and step()
returns when the slowest is done, so every world is at the same sim time after each
period. read() gathers the shards' readings into the fleet's arrays, write() scatters
the commands; the loop, controllers and bridge see one system and never the devices.

A shard is an ordinary backend system of its device: it checks its worlds' commands,
freezes its diverged worlds and grows its own buffers; its status rows are the fleet's.
Cameras and lidars render and cast on each shard; sensor noise is the fleet's, seeded by
fleet world numbers, so a world's noise does not depend on how many devices there are.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from batchsim.hardware import BatchedSystem, CallbackReturn, LifecycleState, ReturnType
from batchsim.model import RobotSpec
from batchsim.sensors import Camera, Lidar, SensorConfig


def split(nworld: int, nshard: int) -> list[range]:
    """Contiguous world ranges, as even as possible, the larger ones first."""
    if not 1 <= nshard <= nworld:
        raise ValueError(f"{nworld} worlds cannot be split over {nshard} devices")
    base, extra = divmod(nworld, nshard)
    ranges, start = [], 0
    for i in range(nshard):
        size = base + (i < extra)
        ranges.append(range(start, start + size))
        start += size
    return ranges


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
      **options: the backend's options, given to every shard.

    Attributes:
      shards: the per-device systems, in world order.
      world_ranges: the worlds of each shard.
      devices: the device of each shard.
    """

    OPTIONS: ClassVar[dict[str, Any]] = {}

    def __init__(
        self,
        backend: type[BatchedSystem],
        spec: RobotSpec,
        nworld: int,
        devices: Sequence[Any],
        **options: Any,
    ):
        super().__init__(spec, nworld)
        if "device" not in backend.OPTIONS:
            raise ValueError(f"the {backend.name} backend does not run on devices; it cannot be sharded")
        self.name = backend.name
        self.devices = list(devices)
        self.world_ranges = split(self.nworld, len(self.devices))
        self.shards = [
            backend(spec, len(rows), **{**options, "device": device})
            for rows, device in zip(self.world_ranges, self.devices, strict=True)
        ]
        for shard, rows in zip(self.shards, self.world_ranges, strict=True):
            shard.number_worlds_as(rows.start, self.nworld)  # failure lines name fleet worlds
        self.options = dict(self.shards[0].options, device=self.devices)
        self.sensors_batched = self.shards[0].sensors_batched
        self._pool = ThreadPoolExecutor(len(self.shards), thread_name_prefix="batchsim-shard")
        self._stepped: set[int] = set()  # period lengths every shard has compiled or captured

    def __repr__(self) -> str:
        return f"ShardedSystem({self.name}, {self.nworld} worlds on {self.devices})"

    # --- lifecycle: every shard follows the fleet ---
    def on_init(self) -> CallbackReturn:
        for shard in self.shards:
            shard.initialize()
        return CallbackReturn.SUCCESS

    def on_configure(self, previous_state: LifecycleState) -> CallbackReturn:
        for shard in self.shards:  # one at a time: loading kernels and models is not thread-safe
            shard.configure()
        self._collect()
        return CallbackReturn.SUCCESS

    def on_activate(self, previous_state: LifecycleState) -> CallbackReturn:
        for shard in self.shards:
            shard.activate()
        return CallbackReturn.SUCCESS

    def on_deactivate(self, previous_state: LifecycleState) -> CallbackReturn:
        for shard in self.shards:
            shard.deactivate()
        return CallbackReturn.SUCCESS

    def on_cleanup(self, previous_state: LifecycleState) -> CallbackReturn:
        for shard in self.shards:
            shard.cleanup()
        return CallbackReturn.SUCCESS

    def on_shutdown(self, previous_state: LifecycleState) -> CallbackReturn:
        for shard in self.shards:
            if shard.lifecycle_state is not LifecycleState.FINALIZED:
                shard.shutdown()
        self._pool.shutdown(wait=False)
        return CallbackReturn.SUCCESS

    def on_error(self, previous_state: LifecycleState) -> CallbackReturn:
        for shard in self.shards:
            if shard.lifecycle_state not in (LifecycleState.UNKNOWN, LifecycleState.FINALIZED):
                shard.error()
        return CallbackReturn.SUCCESS

    # --- the contract, over the shards ---
    def read(self, time: float | None = None, period: float | None = None) -> ReturnType:
        if self.lifecycle_state not in (LifecycleState.INACTIVE, LifecycleState.ACTIVE):
            return ReturnType.OK
        # every device's download at once: each waits on its own device, not on the others
        self._each(lambda shard: shard.read(time, period))
        self._collect()
        self._add_noise()  # frozen worlds keep their held, noise-free readings
        return ReturnType.OK

    def write(self, time: float | None = None, period: float | None = None) -> ReturnType:
        if self.lifecycle_state is not LifecycleState.ACTIVE:
            return ReturnType.OK
        command = self._command
        for shard, rows in zip(self.shards, self.world_ranges, strict=True):
            shard.command[:] = command[rows.start : rows.stop]
        self._each(lambda shard: shard.write(time, period))  # every device's upload at once
        for shard, rows in zip(self.shards, self.world_ranges, strict=True):
            self.status[rows.start : rows.stop] = shard.status
        return ReturnType.OK

    def step(self, nstep: int = 1) -> None:
        """Advance every world `nstep` steps, every device at once; returns when all are done."""
        self._require("step", frozenset({LifecycleState.INACTIVE, LifecycleState.ACTIVE}))
        if nstep < 1:
            raise ValueError(f"nstep must be >= 1, got {nstep}")
        if nstep in self._stepped:
            self._each(lambda shard: shard.step(nstep))
        else:  # the first period of a length compiles or captures it: one device at a time
            for shard in self.shards:
                shard.step(nstep)
            self._stepped.add(nstep)
        for shard, rows in zip(self.shards, self.world_ranges, strict=True):
            self.status[rows.start : rows.stop] = shard.status

    def reset(self, worlds: Sequence[int] | np.ndarray | None = None) -> None:
        """Reset all or the listed worlds (fleet numbering), each on its shard."""
        self._require(
            "reset", frozenset({LifecycleState.UNCONFIGURED, LifecycleState.INACTIVE, LifecycleState.ACTIVE})
        )
        rows = self._worlds(worlds)
        for shard, r in zip(self.shards, self.world_ranges, strict=True):
            local = None if rows is None else rows[(rows >= r.start) & (rows < r.stop)] - r.start
            if local is None or local.size:
                shard.reset(local)
                sel = slice(None) if local is None else local
                self._command[r.start : r.stop][sel] = shard.command[sel]
            else:
                shard.read()  # reset refreshes every world's readings, as on one device
        self._collect()
        self._add_noise()  # frozen worlds keep their held, noise-free readings

    def device_arrays(self) -> dict[str, PerDevice]:
        """The live device arrays of every shard (see the backend's device_arrays), field by
        field: `arrays["qpos"][i]` is device i's (its worlds are `world_ranges[i]`), zero copy;
        `np.asarray(arrays["qpos"])` copies the whole fleet's to the host."""
        parts = [shard.device_arrays() for shard in self.shards]
        return {field: PerDevice([p[field] for p in parts]) for field in parts[0]}

    # --- cameras, lidars, noise: rendered on the shards, noise added by the fleet ---
    def set_sensor_config(self, config: SensorConfig | str | Path | Mapping[str, Any]) -> None:
        super().set_sensor_config(config)
        quiet = dataclasses.replace(self._sensor_config, noise={})  # the fleet adds the noise
        for shard in self.shards:
            shard.set_sensor_config(quiet)

    def _render_frames(self, camera: Camera, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        parts = [shard.render(camera.name, local) for shard, local in self._split(worlds)]
        return np.concatenate([p.rgb for p in parts]), np.concatenate([p.depth for p in parts])

    def _device_frames(self, camera: Camera) -> tuple[PerDevice, PerDevice]:
        parts = [shard.render(camera.name, device=True) for shard in self.shards]
        return PerDevice([p.rgb for p in parts]), PerDevice([p.depth for p in parts])

    def _cast_ranges(self, lidar: Lidar, worlds: np.ndarray, copy: bool) -> np.ndarray:
        return np.concatenate([shard.scan(lidar.name, local) for shard, local in self._split(worlds)])

    def _device_ranges(self, lidar: Lidar) -> PerDevice:
        return PerDevice([shard.scan(lidar.name, device=True) for shard in self.shards])

    def _split(self, worlds: np.ndarray) -> list[tuple[BatchedSystem, np.ndarray]]:
        """(shard, its local world indices) for the fleet's `worlds`, ascending, in shard order."""
        out = []
        for shard, r in zip(self.shards, self.world_ranges, strict=True):
            local = worlds[(worlds >= r.start) & (worlds < r.stop)] - r.start
            if local.size:
                out.append((shard, local))
        return out

    # --- helpers ---
    def _each(self, call: Any) -> None:
        """Run `call(shard)` for every shard at once; re-raise the first failure."""
        for future in [self._pool.submit(call, shard) for shard in self.shards]:
            future.result()

    def _collect(self) -> None:
        """The shards' readings and status into the fleet's arrays."""
        for shard, r in zip(self.shards, self.world_ranges, strict=True):
            rows = slice(r.start, r.stop)
            self.state[rows] = shard.state
            if self.base_state is not None:
                self.base_state[rows] = shard.base_state
            self.time[rows] = shard.time
            for name, values in shard.sensordata.items():
                self.sensordata[name][rows] = values
            self.status[rows] = shard.status
