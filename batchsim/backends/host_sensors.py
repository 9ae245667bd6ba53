"""Rendering and ray casting on the CPU, over the worlds of a `mujoco.batch.Batch`.

The cpu backend hands in its own batch; mjx hands in a host mirror whose state rows it
fills from the device first ("through the host copy"). Per world, the state is loaded into
one scratch MjData and its kinematics computed (mj_kinematics, mj_camlight: a few
microseconds), so images and scans show the current state, as on warp.

Rendering is MuJoCo's OpenGL renderer, offscreen: EGL (a GPU's, or Mesa's software
rasterizer where there is none), or OSMesa; one sample per pixel and no shadows, as MuJoCo
Warp renders. With MUJOCO_GL unset on a machine without a
display, EGL is tried first, then OSMesa. One render per world and camera reads colour
and depth together; depth comes back in metres along the optical axis, with +inf where
nothing was hit (REP 117/118). Ray casting is mujoco.batch's `ray`, threaded over worlds
in C.

`submit` renders on a thread of its own instead, with its own GL context, from a copy of
the worlds' poses taken at the call: the caller (the control loop) steps the physics while
the frames are drawn on another core (MuJoCo's renderer releases the GIL).
"""

from __future__ import annotations

import copy
import os
import sys
from concurrent.futures import Future, ThreadPoolExecutor

import mujoco
import numpy as np
from mujoco import batch as mjbatch

from batchsim.sensors.camera import Camera
from batchsim.sensors.lidar import Lidar


class RenderingUnavailable(RuntimeError):
    """No OpenGL for MuJoCo's renderer on this machine: the message says what to install."""


_GL_HINT = (
    "MuJoCo's renderer needs OpenGL: on Debian/Ubuntu `apt-get install libegl1 libgl1-mesa-dri` "
    "(EGL, software or GPU), or `libosmesa6` with MUJOCO_GL=osmesa"
)


def gl_context_class() -> type:
    """MuJoCo's GLContext class for offscreen rendering here."""
    choice = os.environ.get("MUJOCO_GL", "").lower().strip()
    headless = sys.platform.startswith("linux") and not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY")
    if choice in ("", "egl") and (headless or choice == "egl"):
        try:
            from mujoco.egl import GLContext

            return GLContext
        except Exception as e:  # noqa: BLE001  (no libEGL, or PyOpenGL set to another platform)
            if choice == "egl":
                raise RenderingUnavailable(f"EGL is not available ({e}); {_GL_HINT}") from None
        try:
            from mujoco.osmesa import GLContext

            return GLContext
        except Exception as e:  # noqa: BLE001
            raise RenderingUnavailable(f"neither EGL nor OSMesa is available ({e}); {_GL_HINT}") from None
    return mujoco.GLContext


class _Renderer:
    """One GL context and MuJoCo render context, with an offscreen buffer for the largest camera."""

    def __init__(self, m: mujoco.MjModel, width: int, height: int):
        m = copy.copy(m)  # the offscreen buffer's size and sampling live in the model: change a copy
        m.vis.global_.offwidth = max(int(m.vis.global_.offwidth), width)
        m.vis.global_.offheight = max(int(m.vis.global_.offheight), height)
        # one sample per pixel, as MuJoCo Warp renders: 4x multisampling cost 3-5x the time on
        # Mesa's software rasterizer (320x240, this project's 2-core CI machine)
        m.vis.quality.offsamples = 0
        self.width, self.height = width, height
        try:
            self.gl = gl_context_class()(m.vis.global_.offwidth, m.vis.global_.offheight)
            self.gl.make_current()
        except RenderingUnavailable:
            raise
        except Exception as e:  # noqa: BLE001  (EGL/OSMesa report failures in many types)
            raise RenderingUnavailable(f"could not create an OpenGL context ({e}); {_GL_HINT}") from None
        self.context = mujoco.MjrContext(m, mujoco.mjtFontScale.mjFONTSCALE_100.value)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self.context)
        self.context.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self.scene = mujoco.MjvScene(m, maxgeom=max(1000, 2 * m.ngeom + 100))
        # no shadows, as MuJoCo Warp renders by default: a shadow map is a 4096^2 render per light,
        # 100x the cost of a 320x240 image on a software rasterizer
        self.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        self.option = mujoco.MjvOption()
        # what a real camera would not see: sites and rangefinder rays (as mujoco_ros2_control)
        self.option.sitegroup[:] = 0
        self.option.flags[mujoco.mjtVisFlag.mjVIS_RANGEFINDER] = 0
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        extent = float(m.stat.extent)
        self.near = np.float32(m.vis.map.znear * extent)
        self.far = np.float32(m.vis.map.zfar * extent)
        n, f = float(self.near), float(self.far)
        self._c = np.float32(n / (f - n))  # -(-(f + n) / (f - n)) / 2 - 1/2
        self._d = np.float32(f * n / (f - n))
        self._scratch: tuple[np.ndarray, np.ndarray] | None = None

    def close(self) -> None:
        if self.gl is not None:
            self.gl.make_current()
            self.context.free()
            self.gl.free()
            self.gl = None

    def depth_to_metres(self, raw: np.ndarray, out: np.ndarray) -> None:
        """Reversed-Z depth buffer values (H, W) float32 as OpenGL reads them (bottom row first, 0 at
        the far plane) to metres along the optical axis in out (H, W), top row first, +inf at the far
        plane: MuJoCo's perspective projection undone, as mujoco.Renderer does.

        The arithmetic runs on `raw` as read, contiguous (numpy runs at half speed on a row-reversed
        view), and the far plane's pixels are found once: 45 us a 320x240 frame instead of 100
        (this project's 2-core machine), the same values."""
        denominator, far = self._depth_scratch(raw.shape)
        np.add(raw, self._c, out=denominator)
        np.less_equal(raw, 0.0, out=far)
        if far.any():  # d / +0 = +inf: the far plane
            np.copyto(denominator, 0.0, where=far)
        with np.errstate(divide="ignore"):
            np.divide(self._d, denominator, out=out[::-1])

    def _depth_scratch(self, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) float32 and bool scratch arrays, kept between frames of one size."""
        if self._scratch is None or self._scratch[0].shape != shape:
            self._scratch = (np.empty(shape, np.float32), np.empty(shape, bool))
        return self._scratch


_POSES = ("qpos", "mocap_pos", "mocap_quat")  # what mj_kinematics reads of a world's state


class HostSensors:
    """Cameras and lidars of the worlds of a batch, computed on the CPU.

    Args:
      m: the model.
      batch: the worlds; their state rows are what is rendered and scanned.
    """

    def __init__(self, m: mujoco.MjModel, batch: mjbatch.Batch):
        self.model = m
        self.batch = batch
        self._data = mujoco.MjData(m)
        self._renderer: _Renderer | None = None
        self._frames: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # per camera, a row per world
        # the batch's live rows of what kinematics reads: a render needs no more of a world
        self._rows = {f: batch.bind(f) for f in _POSES if getattr(self._data, f).size}
        self._background: _RenderThread | None = None
        self._kinematics: tuple[dict[str, np.ndarray], mjbatch.Batch] | None = None  # site_poses' batch

    def frames(self, camera: Camera, worlds: np.ndarray, copy: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Render `camera` in `worlds`: (n, H, W, 3) uint8 and (n, H, W) float32, with `copy` new
        arrays rendered into, else views of this object's buffers, which the next call for this
        camera overwrites."""
        if copy:  # rendered straight into the caller's arrays: no second pass over the frames
            rgb = np.empty((len(worlds), camera.height, camera.width, 3), np.uint8)
            depth = np.empty((len(worlds), camera.height, camera.width), np.float32)
            self.render(camera, worlds, rgb, depth)
            return rgb, depth
        if camera.name not in self._frames:  # filled from the first row: a call for n worlds uses n rows
            nsim = self.batch.nsim
            self._frames[camera.name] = (
                np.empty((nsim, camera.height, camera.width, 3), np.uint8),
                np.empty((nsim, camera.height, camera.width), np.float32),
            )
        rgb, depth = (a[: len(worlds)] for a in self._frames[camera.name])
        self.render(camera, worlds, rgb, depth)
        return rgb, depth

    def poses(self, worlds: np.ndarray) -> dict[str, np.ndarray]:
        """Copies of the rows of `worlds` that a render reads (qpos (n, nq), mocap_pos, mocap_quat)."""
        rows = np.asarray(worlds, np.intp)
        return {f: bound[rows] for f, bound in self._rows.items()}

    def render(self, camera: Camera, worlds: np.ndarray, rgb_out: np.ndarray, depth_out: np.ndarray) -> None:
        """Render `camera` in each of `worlds` into rgb_out (n, H, W, 3) uint8 and depth_out (n, H, W) float32.

        Images are top row first (ROS), depth in metres along the optical axis, +inf where
        the ray met nothing before the far plane.
        """
        self._renderer = _fitted(self._renderer, self.model, camera.width, camera.height)
        _draw(self.model, self._renderer, self._data, camera, self.poses(worlds), rgb_out, depth_out)

    def submit(self, camera: Camera, worlds: np.ndarray) -> Future[tuple[np.ndarray, np.ndarray]]:
        """Start rendering `camera` in `worlds` as they are now, on this object's render thread
        (its own OpenGL context), and return at once; the future's result is (n, H, W, 3) uint8
        and (n, H, W) float32 arrays of its own, as `render` fills. Jobs run in order."""
        if self._background is None:
            self._background = _RenderThread(self.model)
        return self._background.submit(camera, len(worlds), self.poses(worlds))

    def prepare(self, cameras: list[Camera]) -> None:
        """Start the render thread and make its GL context, for the largest of `cameras`, now:
        making a context holds Python's GIL for ~0.2 s (MuJoCo's MjrContext; measured on Mesa's
        software rasterizer), which in a running control loop would be a stalled period."""
        if not cameras:
            return
        if self._background is None:
            self._background = _RenderThread(self.model)
        self._background.prepare(max(c.width for c in cameras), max(c.height for c in cameras))

    def close(self) -> None:
        """Free the renderers (after the render thread's pending jobs)."""
        if self._background is not None:
            self._background.close()
            self._background = None
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def site_poses(self, site: int, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Site `site`'s world position (n, 3) and rotation matrix (n, 3, 3) float64 in each of
        `worlds` at their current state (not the last step's kinematics, a substep behind).

        mj_kinematics on a kinematics-only batch beside the worlds' own (their state rows
        copied in, contacts and constraints off), threaded in C: a Python loop over worlds cost
        more per world than casting a 360-ray scan on 16 cores (H200 host, 1024 worlds)."""
        rows = np.asarray(worlds, np.intp)
        kinematics = self._kinematics_batch()
        for field, bound in self._rows.items():
            kinematics[0][field][rows] = bound[rows]
        ids = None if len(rows) == self.batch.nsim else np.unique(rows)  # the batch takes them sorted
        kinematics[1].forward(ids, stage=mujoco.mjtStage.mjSTAGE_POS.value)
        return kinematics[0]["site_xpos"][rows, site], kinematics[0]["site_xmat"][rows, site].reshape(-1, 3, 3)

    def _kinematics_batch(self) -> tuple[dict[str, np.ndarray], mjbatch.Batch]:
        if self._kinematics is None:
            m = copy.copy(self.model)  # what mj_fwdPosition does beyond kinematics, off: no collisions
            m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
            batch = mjbatch.Batch(m, self.batch.nsim, nthread=self.batch.nthread)
            bound = {f: batch.bind(f) for f in (*self._rows, "site_xpos", "site_xmat")}
            self._kinematics = (bound, batch)
        return self._kinematics

    def cast(self, lidar: Lidar, worlds: np.ndarray) -> np.ndarray:
        """(n, nray) float64 distances along `lidar`'s rays in each of `worlds`; -1 where a ray hit nothing."""
        n = len(worlds)
        origin, rotation = self.site_poses(lidar.site_id, worlds)
        vec = np.einsum("nij,rj->nri", rotation, lidar.directions)
        every = n == self.batch.nsim and bool((np.asarray(worlds) == np.arange(n)).all())
        if every:
            ids = None
        else:  # the batch takes ids sorted: cast in ascending order, give rows back in the order asked
            order = np.argsort(worlds, kind="stable")
            ids = np.asarray(worlds, np.int32)[order]
            origin, vec = origin[order], vec[order]
        dist, _ = self.batch.ray(origin[:, None, :], vec, bodyexclude=lidar.body_id, ids=ids)
        if not every:
            dist[order] = dist.copy()
        return dist


def _fitted(r: _Renderer | None, m: mujoco.MjModel, width: int, height: int) -> _Renderer:
    """`r`, or a new renderer where `r` is None or its offscreen buffer is smaller than
    `width` x `height`; current in the calling thread either way (a GL context is current per
    thread)."""
    if r is None or r.width < width or r.height < height:
        if r is not None:
            r.close()
        return _Renderer(m, max(width, r.width if r else 0), max(height, r.height if r else 0))
    r.gl.make_current()  # the caller's thread may have made another context current since
    return r


def _draw(
    m: mujoco.MjModel,
    r: _Renderer,
    d: mujoco.MjData,
    camera: Camera,
    poses: dict[str, np.ndarray],
    rgb_out: np.ndarray,
    depth_out: np.ndarray,
) -> None:
    """Render `camera` in each world whose pose rows `poses` holds (HostSensors.poses), with the
    scratch data `d`, into rgb_out (n, H, W, 3) uint8 and depth_out (n, H, W) float32."""
    viewport = mujoco.MjrRect(0, 0, camera.width, camera.height)
    r.camera.fixedcamid = camera.id
    # one world's pixels as OpenGL reads them, bottom row first
    rgb = np.empty((camera.height, camera.width, 3), np.uint8)
    depth = np.empty((camera.height, camera.width), np.float32)
    targets = [(getattr(d, field), rows) for field, rows in poses.items()]
    for k in range(len(rgb_out)):
        for target, rows in targets:
            target[:] = rows[k]
        mujoco.mj_kinematics(m, d)
        mujoco.mj_camlight(m, d)
        mujoco.mjv_updateScene(m, d, r.option, None, r.camera, mujoco.mjtCatBit.mjCAT_ALL.value, r.scene)
        mujoco.mjr_render(viewport, r.scene, r.context)
        mujoco.mjr_readPixels(rgb, depth, viewport, r.context)
        rgb_out[k] = rgb[::-1]  # OpenGL's rows start at the bottom
        r.depth_to_metres(depth, depth_out[k])


class _RenderThread:
    """One thread that renders snapshots of worlds in order, with a GL context of its own (made,
    used and freed on that thread): MuJoCo's renderer releases the GIL, so the caller steps the
    physics meanwhile on another core."""

    def __init__(self, m: mujoco.MjModel):
        self.model = m
        self._data = mujoco.MjData(m)
        self._renderer: _Renderer | None = None
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="batchsim-render")

    def submit(self, camera: Camera, n: int, poses: dict[str, np.ndarray]) -> Future[tuple[np.ndarray, np.ndarray]]:
        return self._pool.submit(self._render, camera, n, poses)

    def prepare(self, width: int, height: int) -> None:
        """Make the thread's renderer for images up to `width` x `height`; return when it is made."""
        self._pool.submit(self._fit, width, height).result()

    def close(self) -> None:
        self._pool.submit(self._free).result()
        self._pool.shutdown(wait=True)

    def _fit(self, width: int, height: int) -> None:
        self._renderer = _fitted(self._renderer, self.model, width, height)

    def _render(self, camera: Camera, n: int, poses: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        rgb = np.empty((n, camera.height, camera.width, 3), np.uint8)
        depth = np.empty((n, camera.height, camera.width), np.float32)
        self._fit(camera.width, camera.height)
        _draw(self.model, self._renderer, self._data, camera, poses, rgb, depth)
        return rgb, depth

    def _free(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
