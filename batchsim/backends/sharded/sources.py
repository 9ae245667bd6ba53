"""What a fleet over several devices renders, casts and poses, from its shards: the source of its
Sensing and BodyPoses parts (batchsim.parts), and each device's own arrays side by side
(`PerDevice`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import Future
from typing import Any

import numpy as np

from batchsim.backends.sharded.shards import ShardOp
from batchsim.sensors import Camera, Lidar


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


class ShardSources:
    """The fleet's images, rays and poses, from its shards (the Sensing and BodyPoses parts'
    source): a render or scan of some worlds is each shard's of its own, concatenated."""

    def __init__(self, fleet: Any):  # a ShardedSystem: its shards, asked through each(), run() and split()
        self._fleet = fleet
        # tf's poses of every world: asked for since the last read (the next read brings them along),
        # and whether the fleet's pose rows are the engine's current ones (no shard op changed them since)
        self.poses_wanted = self.poses_current = False

    def render_frames(self, camera: Camera, worlds: np.ndarray, copy: bool) -> tuple[np.ndarray, np.ndarray]:
        f = self._fleet  # the shards' parts concatenated: arrays of the caller's own whatever `copy` says
        parts = f.run([(s, ShardOp.RENDER, (camera.name, local)) for s, local in f.split(worlds)], f.processes)
        return np.concatenate([p.rgb for p in parts]), np.concatenate([p.depth for p in parts])

    def render_frames_later(self, camera: Camera, worlds: np.ndarray) -> Future:
        future: Future = Future()
        future.set_result(self.render_frames(camera, worlds, True))
        return future

    def prepare_rendering(self, cameras: list[Camera]) -> None:
        pass

    def device_frames(self, camera: Camera) -> tuple[PerDevice, PerDevice]:
        f = self._fleet
        if f.processes:  # host copies, from each shard process (see device_arrays)
            parts = f.each(ShardOp.DEVICE_FRAMES, camera.name)
        else:
            parts = [shard.system.render(camera.name, device=True) for shard in f.shards]  # type: ignore[union-attr]
        return PerDevice([p.rgb for p in parts]), PerDevice([p.depth for p in parts])

    def cast_ranges(self, lidar: Lidar, worlds: np.ndarray, copy: bool) -> np.ndarray:
        f = self._fleet
        return np.concatenate(f.run([(s, ShardOp.SCAN, (lidar.name, local)) for s, local in f.split(worlds)], f.processes))

    def device_ranges(self, lidar: Lidar, host: Callable[[], np.ndarray]) -> PerDevice:
        f = self._fleet
        if f.processes:  # host copies, from each shard process (see device_arrays)
            return PerDevice(f.each(ShardOp.DEVICE_RANGES, lidar.name))
        return PerDevice([shard.system.scan(lidar.name, device=True) for shard in f.shards])  # type: ignore[union-attr]

    def pose_rows(self) -> tuple[np.ndarray, np.ndarray]:
        # every world, as tf asks each period: in the fleet's rows, nothing pickled nor copied here;
        # brought by this period's read where tf asked last period too, else fetched now
        f = self._fleet
        self.poses_wanted = True
        if not self.poses_current:
            f.each(ShardOp.POSES)
            self.poses_current = True
        return f.memory["xpos"], f.memory["xquat"]

    def body_poses(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # each shard's worlds in ascending order, then put back in the order asked for
        f, nbody = self._fleet, self._fleet.model.nbody
        order = np.argsort(worlds, kind="stable")
        parts = f.run([(s, ShardOp.BODY_POSES, (local,)) for s, local in f.split(worlds[order])], f.processes)
        xpos, xquat = np.empty((len(worlds), nbody, 3)), np.empty((len(worlds), nbody, 4))
        if parts:
            xpos[order], xquat[order] = np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
        return xpos, xquat
