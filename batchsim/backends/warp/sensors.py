"""Cameras and lidars on MuJoCo Warp (`Sensors`): its ray-traced rendering and ray casting, every
world in one launch, each camera's or lidar's launches captured in a graph and replayed.
"""

from __future__ import annotations

import contextlib
from typing import Any

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp
from mujoco_warp._src import types as _warp_types  # vec6, the geom-group mask rays() takes

from batchsim.backends.warp.host import host_array
from batchsim.backends.warp.kernels import CPU_GRAPHS
from batchsim.backends.warp.worlds import DeviceWorlds, Graphs
from batchsim.sensors import Camera, Lidar


class Sensors:
    """The engine's cameras and lidars: their render contexts, ray buffers and graphs, made on
    first use and kept until the engine closes its sensors.

    Attributes:
      graphs: each camera's and lidar's launches, captured (they take the Data's arrays: the
        engine clears them when its buffers grow).
    """

    def __init__(self, worlds: DeviceWorlds, capture: bool):
        self._worlds = worlds
        self.graphs = Graphs(worlds.device, capture)
        self._cameras: dict[str, Any] = {}  # per camera: (render context, rgb, depth, host rgb, host depth)
        self._lidars: dict[str, dict[str, wp.array]] = {}  # per lidar: its rays and results, on the device and host
        m = worlds.model
        modes = (int(mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM), int(mujoco.mjtCamLight.mjCAMLIGHT_TARGETBODYCOM))
        # whether a camera or light tracks a centre of mass (com_pos needed)
        self._com_pos = bool(np.isin(m.cam_mode, modes).any() or np.isin(m.light_mode, modes).any())

    def _kinematics(self, cameras: bool) -> None:
        """Positions of bodies, geoms and sites (and cameras, lights) from the current qpos.

        After a step they describe the state before its last substep, and after a reset they
        are stale; images and scans show the current state, as on cpu.
        """
        w = self._worlds
        m, d = w.m, w.d
        mjw.kinematics(m, d)
        if cameras:
            if self._com_pos:
                mjw.com_pos(m, d)
            mjw.camlight(m, d)

    def _run(self, key: str, program: Any) -> None:
        """Run `program` (a camera's or lidar's launches, on buffers fixed until they grow). With
        graphs on, it runs eagerly the first time (kernels compile, the renderer specializes),
        is captured then, and is replayed after: one launch per call, not ten launches'
        argument packing in Python (a render of 1 world at 4x4 on Warp's CPU device: 1.1 ms a
        call launched one by one, 30 us replayed)."""
        graphs = self.graphs
        if not graphs.enabled:
            program()
            return
        serial = CPU_GRAPHS if not graphs.cuda else contextlib.nullcontext()
        with serial:
            graph = graphs.get(key)
            if graph is None:
                program()
                graphs.capture(key, program)
            else:
                wp.capture_launch(graph)

    def device_frames(self, camera: Camera) -> tuple[wp.array, wp.array]:
        """Every world's images of `camera` on the device: (nworld, H, W, 3) uint8 and (nworld, H, W)
        float32 Warp arrays, overwritten by the next render of this camera."""
        w = self._worlds
        entry = self._cameras.get(camera.name)
        with wp.ScopedDevice(w.device):
            if entry is None:
                rc = mjw.create_render_context(
                    w.model,
                    nworld=w.nworld,
                    cam_res=[(camera.width, camera.height)],
                    render_rgb=True,
                    render_depth=True,
                    cam_active=[camera.id],
                )
                shape = (w.nworld, camera.height, camera.width)
                entry = self._cameras[camera.name] = (
                    rc,
                    wp.zeros((*shape, 3), dtype=wp.uint8),
                    wp.zeros(shape, dtype=wp.float32),
                    host_array((*shape, 3), wp.uint8, w.cuda),
                    host_array(shape, wp.float32, w.cuda),
                )
            rc, rgb, depth = entry[:3]

            def program() -> None:
                self._kinematics(cameras=True)
                mjw.refit_bvh(w.m, w.d, rc)
                mjw.render(w.m, w.d, rc)
                wp.launch(_unpack_frames, dim=depth.shape, inputs=[rc.rgb_data, rc.depth_data], outputs=[rgb, depth])

            self._run(f"camera {camera.name}", program)
        return rgb, depth

    def frames(self, camera: Camera, worlds: np.ndarray, copy: bool) -> tuple[np.ndarray, np.ndarray]:
        """Host (n, H, W, 3) uint8 and (n, H, W) float32 images of `camera` in `worlds` (ascending)."""
        w = self._worlds
        rgb, depth = self.device_frames(camera)
        host_rgb, host_depth = self._cameras[camera.name][3:]
        with wp.ScopedDevice(w.device):
            if w.cuda:
                wp.copy(host_rgb, rgb)
                wp.copy(host_depth, depth)
            else:
                host_rgb, host_depth = rgb, depth
            wp.synchronize_device(w.device)
        rgb_np, depth_np = host_rgb.numpy(), host_depth.numpy()
        if len(worlds) == w.nworld:  # every world: the buffers themselves, or one copy of them
            return (rgb_np.copy(), depth_np.copy()) if copy else (rgb_np, depth_np)
        return rgb_np[worlds], depth_np[worlds]  # fancy indexing: a copy

    def ranges(self, lidar: Lidar, worlds: np.ndarray, copy: bool) -> np.ndarray:
        """Host (n, nray) float32 REP 117 ranges of a ray-casting `lidar` in `worlds`, cast now."""
        w = self._worlds
        b = self.cast(lidar)
        host = b["host"]
        with wp.ScopedDevice(w.device):
            if w.cuda:
                wp.copy(host, b["ranges"])  # one copy, into pinned memory: a DMA
            else:
                host = b["ranges"]
            wp.synchronize_device(w.device)
        ranges = host.numpy()
        if len(worlds) < w.nworld:
            return ranges[worlds]  # fancy indexing: a copy
        return ranges.copy() if copy else ranges

    def cast(self, lidar: Lidar) -> dict[str, wp.array]:
        """Cast `lidar`'s rays in every world now; its buffers, "ranges" holding the (nworld, nray)
        REP 117 ranges on the device, overwritten by the next scan of this lidar."""
        w = self._worlds
        buffers = self._lidars.get(lidar.name)
        shape = (w.nworld, lidar.nray)
        with wp.ScopedDevice(w.device):
            if buffers is None:
                buffers = self._lidars[lidar.name] = {
                    "directions": wp.array(lidar.directions.astype(np.float32), dtype=wp.vec3),
                    "exclude": wp.full(lidar.nray, lidar.body_id, dtype=wp.int32),
                    "pnt": wp.zeros(shape, dtype=wp.vec3),
                    "vec": wp.zeros(shape, dtype=wp.vec3),
                    "dist": wp.zeros(shape, dtype=wp.float32),
                    "geomid": wp.zeros(shape, dtype=wp.int32),
                    "normal": wp.zeros(shape, dtype=wp.vec3),
                    "ranges": wp.zeros(shape, dtype=wp.float32),
                    "host": host_array(shape, wp.float32, w.cuda),
                }
            b = buffers
            everything = _warp_types.vec6(-1.0, -1.0, -1.0, -1.0, -1.0, -1.0)  # every geom group

            def program() -> None:
                self._kinematics(cameras=False)
                d = w.d
                wp.launch(
                    _lidar_rays,
                    dim=shape,
                    inputs=[d.site_xpos, d.site_xmat, lidar.site_id, b["directions"]],
                    outputs=[b["pnt"], b["vec"]],
                )
                mjw.rays(w.m, d, b["pnt"], b["vec"], everything, True, b["exclude"], b["dist"], b["geomid"], b["normal"])
                # REP 117 on the device: the host gets float32 ranges in one copy, nothing left to convert
                wp.launch(
                    _lidar_ranges,
                    dim=shape,
                    inputs=[b["dist"], float(lidar.range_min), float(lidar.range_max)],
                    outputs=[b["ranges"]],
                )

            self._run(f"lidar {lidar.name}", program)
        return b


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
