"""Cameras and lidars through the contract against the raw libraries, per backend and world count.

The scene is the shipped `rover` (a diff-drive base in a room with obstacles) with its
camera at each --sizes resolution, RGB-D, and its 360-ray lidar. Each world drives its own
constant wheel command for a second first, so that every world sees something different.

Throughput (frames/s = worlds x renders / seconds; scans/s likewise), in one process,
interleaved rounds, compile / context creation / graph capture excluded:

  camera   contract  sim.render(camera): new host arrays, (n, H, W, 3) uint8 + (n, H, W) float32
           reused    sim.render(camera, copy=False): host arrays the next render overwrites, as
                     the raw loops reuse theirs (cpu, mjx; warp's device column is its like)
           device    sim.render(camera, device=True): the backend's own arrays (warp, mjx)
           raw       the library doing the same rendering, synchronized:
             cpu   per world mujoco.batch get_data, mj_kinematics, mj_camlight, mjv_updateScene,
                   mjr_render, mjr_readPixels (RGB and depth in one read), one GL context, and
                   rows flipped and depth in metres, as mujoco.Renderer does
             mjx   one download of qpos, then the cpu loop on a host batch (the rover's
                   obstacles do not collide on mjx: `mjx_rover()`)
             warp  mjw.kinematics + camlight, refit_bvh, render, get_rgb + get_depth (device),
                   launched one by one
           raw graph  (warp) the same launches captured once in a graph and replayed, as
                   MuJoCo Warp's own benchmarks run them
  lidar    contract  sim.scan(lidar): (n, 360) float32 ranges on the host
           raw       the same rays: cpu/mjx mujoco.batch's ray from bound site poses; warp a
                     ray kernel + mjw.rays + the distances to the host (`.numpy()`), launched
                     one by one (raw) or replayed from a graph (raw graph)
           on the device (warp)  sim.scan(lidar, device=True) against the same raw casts
                     without the host copy

ratio: the project's best (device, reused or contract; the host scan for the lidar row) over the
raw library's best (raw or raw graph).

The loop section (--loop) runs the physics at --control-rate with the camera at
--camera-rate and the lidar at --lidar-rate for every world, as fast as it goes, through
SensorSampler (the participant the ROS bridge will use), and reports the real-time factor
held, frames/s, and the median and worst control period; benchmarks/sensor_loop_profile.py
breaks that period down by phase, beside the same model's physics-only rate.

The ROS section (--ros) runs the same loop as the `batchsim` command with the bridge
(`--rtf 0` flat out, or paced with --ros-rtf 1; its bridge workers), while subscriber
processes take every world's image_raw, depth/image_raw and scan (raw, not deserialized):
the RTF held (median and worst one-second window), frames/s, depth frames/s and scans/s
received, what the fleet produced per wall second (worlds x rate x RTF), and the cores the
physics process, its bridge workers and the subscribers used meanwhile (Linux /proc).

    python benchmarks/sensors.py --backends cpu --worlds 16,256 --sizes 64x64,320x240
    python benchmarks/sensors.py --backends warp,mjx,cpu --worlds 16,256,1024,4096 --loop 1024
    python benchmarks/sensors.py --backends cpu --no-camera --no-lidar --loop 16 --ros 16    # with and without ROS
    python benchmarks/sensors.py --backends cpu --no-camera --no-lidar --loop 16 --loop-size 320x240 \
        --camera-rate 10 --ros 16 --ros-rtf 1 --subscriber-processes 1               # the 2-core target
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # a source checkout, uninstalled

from fleet import Batchsim, _pythonpath, children  # noqa: E402 (its process handling and status parsing)
from throughput import device_name, versions  # noqa: E402

import batchsim  # noqa: E402
from batchsim.loop.sampler import SensorSampler  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
LOCALHOST = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
MODEL = "rover"
CAMERA = "front_camera"
LIDAR = "base_scan"
DRIVE_SECONDS = 1.0


def mjx_rover() -> str:
    """The rover with its walls, pillars and crates seen but not collided with: MJX has no
    cylinder-box collision (the wheels and mast against the walls and crates), and refuses the
    model. In the one second each world drives before a measurement no rover reaches them."""
    path = Path(tempfile.gettempdir()) / f"batchsim_rover_mjx_{os.getpid()}.xml"
    if not path.exists():
        text = (ROOT / "models" / "rover.xml").read_text()
        wall = '<geom type="box" material="wall" contype="1" conaffinity="1"/>'
        assert wall in text, "models/rover.xml's wall class changed: update mjx_rover()"
        text = text.replace(wall, wall.replace('"1"', '"0"'))
        text = re.sub(r'(<geom name="(pillar|crate)_\d")', r'\1 contype="0" conaffinity="0"', text)
        path.write_text(text)
    return str(path)


def make(backend: str, nworld: int, size: tuple[int, int] | None, **rates: float) -> batchsim.BatchedSystem:
    """The rover fleet, each world driven for a second on its own wheel command; `rates`:
    camera_rate, lidar_rate (Hz). mjx gets `mjx_rover()`."""
    block: dict = dict(rates)
    if size:
        block["camera_resolution"] = list(size)
    model = mjx_rover() if backend == "mjx" else MODEL
    sim = batchsim.make(model, nworld, backend, sensors={"sensors": block} if block else None)
    sim.configure()
    sim.activate()
    rng = np.random.default_rng(0)
    sim.command[:] = rng.uniform(-1.0, 1.0, sim.command.shape)
    substeps = round(0.01 / sim.dt)
    for _ in range(round(DRIVE_SECONDS / 0.01)):
        sim.write()
        sim.step(substeps)
    sim.read()
    return sim


def interleaved(bodies: dict[str, Callable[[], None]], seconds: float, rounds: int = 3) -> dict[str, float]:
    """Median calls/s of each body, measured in rounds whose order rotates."""
    t0 = time.perf_counter()
    for body in bodies.values():
        body()
    per_call = (time.perf_counter() - t0) / len(bodies)
    calls = max(1, round(seconds / rounds / len(bodies) / max(per_call, 1e-6)))
    names = list(bodies)
    out: dict[str, list[float]] = {name: [] for name in names}
    for r in range(rounds):
        for name in names[r % len(names) :] + names[: r % len(names)]:
            t = time.perf_counter()
            for _ in range(calls):
                bodies[name]()
            out[name].append(calls / (time.perf_counter() - t))
    return {name: float(np.median(v)) for name, v in out.items()}


# ---------------------------------------------------------------- raw rendering


def raw_render_cpu(sim: batchsim.BatchedSystem, qpos_source: Callable[[], np.ndarray] | None = None) -> Callable[[], None]:
    """MuJoCo's renderer over the worlds of a mujoco.batch, lowest level: one render and one
    read per world. mjx passes `qpos_source`, the download from its device."""
    import copy

    import mujoco
    from mujoco import batch as mjbatch

    from batchsim.backends.host_sensors import gl_context_class

    cam = sim.sensors.camera(CAMERA)
    m = copy.copy(sim.model)
    m.vis.global_.offwidth = max(m.vis.global_.offwidth, cam.width)
    m.vis.global_.offheight = max(m.vis.global_.offheight, cam.height)
    m.vis.quality.offsamples = 0  # as batchsim renders (and MuJoCo Warp)
    batch = mjbatch.Batch(m, sim.nworld)
    batch.bind("qpos")[:] = qpos_source() if qpos_source else sim.device_arrays()["qpos"]
    gl = gl_context_class()(m.vis.global_.offwidth, m.vis.global_.offheight)
    gl.make_current()
    con = mujoco.MjrContext(m, mujoco.mjtFontScale.mjFONTSCALE_100.value)
    mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, con)
    scn = mujoco.MjvScene(m, maxgeom=1000)
    scn.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
    opt = mujoco.MjvOption()
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
    camera.fixedcamid = cam.id
    d = mujoco.MjData(m)
    rgb = np.empty((sim.nworld, cam.height, cam.width, 3), np.uint8)
    depth = np.empty((sim.nworld, cam.height, cam.width), np.float32)
    frame = np.empty((cam.height, cam.width, 3), np.uint8)
    zbuffer = np.empty((cam.height, cam.width), np.float32)
    rect = mujoco.MjrRect(0, 0, cam.width, cam.height)
    extent = m.stat.extent
    near, far = m.vis.map.znear * extent, m.vis.map.zfar * extent
    c, d_coef = np.float32(near / (far - near)), np.float32(far * near / (far - near))

    def body() -> None:
        gl.make_current()
        if qpos_source is not None:
            batch.bind("qpos")[:] = qpos_source()
        for w in range(sim.nworld):
            batch.get_data(w, d)
            mujoco.mj_kinematics(m, d)
            mujoco.mj_camlight(m, d)
            mujoco.mjv_updateScene(m, d, opt, None, camera, mujoco.mjtCatBit.mjCAT_ALL.value, scn)
            mujoco.mjr_render(rect, scn, con)
            mujoco.mjr_readPixels(frame, zbuffer, rect, con)
            # what makes them an image and a depth map (as mujoco.Renderer does): top row first, metres
            rgb[w] = frame[::-1]
            np.divide(d_coef, zbuffer[::-1] + c, out=depth[w])

    body.keep = (gl, con, batch)  # type: ignore[attr-defined]
    return body


def captured(device, program: Callable[[], None]) -> Callable[[], None]:
    """`program` (Warp launches) run once (kernels load, MuJoCo Warp's renderer specializes),
    then captured in a graph: a call replays it, as MuJoCo Warp's own benchmarks do."""
    import warp as wp

    with wp.ScopedDevice(device):
        program()
        with wp.ScopedCapture(device=device) as capture:
            program()
    graph = capture.graph

    def replay() -> None:
        wp.capture_launch(graph)

    return replay


def raw_render_warp(sim: batchsim.BatchedSystem) -> dict[str, Callable[[], None]]:
    """MuJoCo Warp's rendering on its own Data (qpos copied from the system): kinematics,
    camlight, refit_bvh, render, get_rgb + get_depth, synchronized; "raw" launches them one
    by one, "raw_graph" replays them from a graph captured once (one Data for both)."""
    import mujoco
    import mujoco_warp as mjw
    import warp as wp

    cam = sim.sensors.camera(CAMERA)
    m = sim.model
    mjd = mujoco.MjData(m)
    mujoco.mj_forward(m, mjd)
    qpos = sim.device_arrays()["qpos"]
    with wp.ScopedDevice(sim.device):
        mw = mjw.put_model(m)
        d = mjw.put_data(m, mjd, nworld=sim.nworld, nconmax=sim.nconmax, njmax=sim.njmax)
        wp.copy(d.qpos, qpos)
        rc = mjw.create_render_context(
            m, nworld=sim.nworld, cam_res=[(cam.width, cam.height)], render_rgb=True, render_depth=True, cam_active=[cam.id]
        )
        rgb = wp.zeros((sim.nworld, cam.height, cam.width), dtype=wp.vec3)
        depth = wp.zeros((sim.nworld, cam.height, cam.width), dtype=wp.float32)

    def program() -> None:
        mjw.kinematics(mw, d)
        mjw.camlight(mw, d)
        mjw.refit_bvh(mw, d, rc)
        mjw.render(mw, d, rc)
        mjw.get_rgb(rc, 0, rgb)
        mjw.get_depth(rc, 0, 1.0, depth)

    def body(run: Callable[[], None]) -> Callable[[], None]:
        def call() -> None:
            with wp.ScopedDevice(sim.device):
                run()
                wp.synchronize_device(sim.device)

        call.keep = (mw, d, rc, rgb, depth, run)  # type: ignore[attr-defined]
        return call

    return {"raw": body(program), "raw_graph": body(captured(sim.device, program))}


# ---------------------------------------------------------------- raw ray casting


def raw_scan_cpu(sim: batchsim.BatchedSystem, qpos_source: Callable[[], np.ndarray] | None = None) -> Callable[[], None]:
    """mujoco.batch's threaded ray casting, from the site poses the batch binds."""
    from mujoco import batch as mjbatch

    ld = sim.sensors.lidar(LIDAR)
    batch = mjbatch.Batch(sim.model, sim.nworld)
    batch.bind("qpos")[:] = qpos_source() if qpos_source else sim.device_arrays()["qpos"]
    site_xpos, site_xmat = batch.bind("site_xpos"), batch.bind("site_xmat")
    batch.forward()  # fills the bound site poses

    def body() -> None:
        if qpos_source is not None:
            batch.bind("qpos")[:] = qpos_source()
        pnt = site_xpos[:, ld.site_id][:, None, :]
        vec = np.einsum("nij,rj->nri", site_xmat[:, ld.site_id].reshape(-1, 3, 3), ld.directions)
        batch.ray(pnt, vec, bodyexclude=ld.body_id)

    body.keep = batch  # type: ignore[attr-defined]
    return body


def raw_scan_warp(sim: batchsim.BatchedSystem) -> dict[str, Callable[[], None]]:
    """MuJoCo Warp's ray casting on its own Data: kinematics, a kernel making each world's rays
    from the site pose, mjw.rays; launched one by one ("raw") or replayed from a graph
    ("raw_graph"), the distances then copied to the host (`.numpy()`: a new array), or not
    ("raw_device", "raw_graph_device"). One Data for the four."""
    import mujoco
    import mujoco_warp as mjw
    import warp as wp
    from mujoco_warp._src import types as warp_types

    ld = sim.sensors.lidar(LIDAR)
    m = sim.model
    mjd = mujoco.MjData(m)
    mujoco.mj_forward(m, mjd)

    @wp.kernel
    def rays(
        site_xpos: wp.array2d(dtype=wp.vec3),
        site_xmat: wp.array2d(dtype=wp.mat33),
        site: int,
        directions: wp.array(dtype=wp.vec3),
        pnt: wp.array2d(dtype=wp.vec3),
        vec: wp.array2d(dtype=wp.vec3),
    ):
        w, r = wp.tid()
        pnt[w, r] = site_xpos[w, site]
        vec[w, r] = site_xmat[w, site] @ directions[r]

    shape = (sim.nworld, ld.nray)
    with wp.ScopedDevice(sim.device):
        mw = mjw.put_model(m)
        d = mjw.put_data(m, mjd, nworld=sim.nworld, nconmax=sim.nconmax, njmax=sim.njmax)
        wp.copy(d.qpos, sim.device_arrays()["qpos"])
        mjw.kinematics(mw, d)
        b = {
            "directions": wp.array(ld.directions.astype(np.float32), dtype=wp.vec3),
            "exclude": wp.full(ld.nray, ld.body_id, dtype=wp.int32),
            "pnt": wp.zeros(shape, dtype=wp.vec3),
            "vec": wp.zeros(shape, dtype=wp.vec3),
            "dist": wp.zeros(shape, dtype=wp.float32),
            "geomid": wp.zeros(shape, dtype=wp.int32),
            "normal": wp.zeros(shape, dtype=wp.vec3),
        }
        everything = warp_types.vec6(-1.0, -1.0, -1.0, -1.0, -1.0, -1.0)

    def program() -> None:
        mjw.kinematics(mw, d)
        wp.launch(rays, dim=shape, inputs=[d.site_xpos, d.site_xmat, ld.site_id, b["directions"]], outputs=[b["pnt"], b["vec"]])
        mjw.rays(mw, d, b["pnt"], b["vec"], everything, True, b["exclude"], b["dist"], b["geomid"], b["normal"])

    def body(run: Callable[[], None], to_host: bool) -> Callable[[], None]:
        def call() -> None:
            with wp.ScopedDevice(sim.device):
                run()
                if to_host:
                    b["dist"].numpy()  # to the host, as the contract's scan (a new array, synchronized)
                else:
                    wp.synchronize_device(sim.device)

        call.keep = (mw, d, b, run)  # type: ignore[attr-defined]
        return call

    graph = captured(sim.device, program)
    return {
        "raw": body(program, True),
        "raw_graph": body(graph, True),
        "raw_device": body(program, False),
        "raw_graph_device": body(graph, False),
    }


def mjx_qpos(sim: batchsim.BatchedSystem) -> Callable[[], np.ndarray]:
    import jax

    return lambda: np.asarray(jax.device_get(sim.device_arrays()["qpos"]))


def raw_render(sim: batchsim.BatchedSystem) -> dict[str, Callable[[], None]]:
    """The raw library's rendering bodies by name: "raw", and on warp "raw_graph"."""
    if sim.name == "warp":
        return raw_render_warp(sim)
    return {"raw": raw_render_cpu(sim, mjx_qpos(sim) if sim.name == "mjx" else None)}


def raw_scan(sim: batchsim.BatchedSystem) -> dict[str, Callable[[], None]]:
    """The raw library's ray-casting bodies by name: "raw", and on warp the graph and device ones."""
    if sim.name == "warp":
        return raw_scan_warp(sim)
    return {"raw": raw_scan_cpu(sim, mjx_qpos(sim) if sim.name == "mjx" else None)}


# ---------------------------------------------------------------- measurements


def camera_row(backend: str, nworld: int, size: tuple[int, int], seconds: float) -> dict:
    sim = make(backend, nworld, size)
    t0 = time.perf_counter()
    sim.render(CAMERA)  # context, BVH, kernels
    setup = time.perf_counter() - t0
    bodies: dict[str, Callable[[], None]] = {"contract": lambda: sim.render(CAMERA), **raw_render(sim)}
    if backend != "warp":
        bodies["reused"] = lambda: sim.render(CAMERA, copy=False)
    if backend == "warp":
        import warp as wp

        def device() -> None:
            sim.render(CAMERA, device=True)
            wp.synchronize_device(sim.device)

        bodies["device"] = device
    elif backend == "mjx":
        bodies["device"] = lambda: sim.render(CAMERA, device=True).depth.block_until_ready()
    for body in bodies.values():
        body()
    rates = interleaved(bodies, seconds)
    sim.shutdown()
    row = {f"{k}_fps": v * nworld for k, v in rates.items()}
    row.update(kind="camera", backend=backend, nworld=nworld, size=f"{size[0]}x{size[1]}", setup_s=setup)
    best = max(row.get("device_fps", 0.0), row.get("reused_fps", 0.0), row["contract_fps"])
    row["ratio"] = best / max(row["raw_fps"], row.get("raw_graph_fps", 0.0))
    return row


def lidar_rows(backend: str, nworld: int, seconds: float) -> list[dict]:
    """The host scan against the raw cast with its host copy; on warp also the device scan
    (`scan(lidar, device=True)`, no host copy) against the raw cast without one."""
    sim = make(backend, nworld, None)
    t0 = time.perf_counter()
    sim.scan(LIDAR)
    setup = time.perf_counter() - t0
    bodies: dict[str, Callable[[], None]] = {"contract": lambda: sim.scan(LIDAR), **raw_scan(sim)}
    if backend == "warp":
        import warp as wp

        def device() -> None:
            sim.scan(LIDAR, device=True)
            wp.synchronize_device(sim.device)

        bodies["device"] = device
    for body in bodies.values():
        body()
    rates = {k: v * nworld for k, v in interleaved(bodies, seconds).items()}
    nray = sim.sensors.lidar(LIDAR).nray
    sim.shutdown()
    common = dict(backend=backend, nworld=nworld, size="", setup_s=setup)
    host = {"kind": f"lidar {nray} rays", "contract_fps": rates["contract"], "raw_fps": rates["raw"], **common}
    if "raw_graph" in rates:
        host["raw_graph_fps"] = rates["raw_graph"]
    host["ratio"] = host["contract_fps"] / max(host["raw_fps"], host.get("raw_graph_fps", 0.0))
    rows = [host]
    if "device" in rates:
        dev = {
            "kind": f"lidar {nray} rays, on the device",
            "contract_fps": float("nan"),
            "device_fps": rates["device"],
            "raw_fps": rates["raw_device"],
            "raw_graph_fps": rates["raw_graph_device"],
            **common,
        }
        dev["ratio"] = dev["device_fps"] / max(dev["raw_fps"], dev["raw_graph_fps"])
        rows.append(dev)
    return rows


def loop_row(
    backend: str, nworld: int, size: tuple[int, int], seconds: float, control: float, camera: float, lidar: float
) -> dict:
    """The physics at `control` Hz with every world's camera at `camera` Hz and lidar at `lidar` Hz."""
    sim = make(backend, nworld, size, camera_rate=camera, lidar_rate=lidar)
    suite = sim.sensors
    sampler = SensorSampler(sim)
    for name in (CAMERA, LIDAR):
        suite.want(name)
    substeps = max(1, round(1.0 / (control * sim.dt)))
    period = substeps * sim.dt
    sim.render(CAMERA), sim.scan(LIDAR)  # setup excluded
    periods = []
    t_sim = 0.0
    t0 = time.perf_counter()
    while t_sim < seconds:
        t = time.perf_counter()
        sim.read()
        sampler.update(sim, t_sim, period)
        sim.write()
        sim.step(substeps)
        t_sim += period
        periods.append(time.perf_counter() - t)
    sampler.flush()  # renders still in flight (cpu and mjx draw on a thread) count, and their time
    wall = time.perf_counter() - t0
    frames = sampler.produced[CAMERA]
    scans = sampler.produced[LIDAR]
    sim.shutdown()
    p = np.array(periods) * 1e3
    return {
        "kind": f"loop {control:g} Hz + camera {camera:g} Hz + lidar {lidar:g} Hz",
        "backend": backend,
        "nworld": nworld,
        "size": f"{size[0]}x{size[1]}",
        "rtf": seconds / wall,
        "contract_fps": frames / wall,
        "scans_per_s": scans / wall,
        "period_median_ms": float(np.median(p)),
        "period_worst_ms": float(p.max()),
        "budget_ms": period * 1e3,
    }


# ---------------------------------------------------------------- with ROS publishing

TOPICS = ("front_camera/image_raw", "front_camera/depth/image_raw", "scan")


def subscriber(domain: int, lo: int, hi: int) -> None:
    """Count image, depth and scan messages of worlds lo..hi-1 (raw); print
    `count <wall> <images> <depths> <scans>` every 0.25 s until stdin closes."""
    os.environ.update(LOCALHOST)
    import rclpy
    from rclpy.context import Context
    from rclpy.experimental import EventsExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import Image, LaserScan

    context = Context()
    rclpy.init(context=context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    node = Node(f"sensors_benchmark_{lo}", context=context)
    counts = [0, 0, 0]

    def counter(k: int):
        def callback(msg: bytes) -> None:
            counts[k] += 1

        return callback

    for w in range(lo, hi):
        for k, (topic, kind) in enumerate(zip(TOPICS, (Image, Image, LaserScan), strict=True)):
            node.create_subscription(kind, f"/world_{w}/{topic}", counter(k), QoSProfile(depth=2), raw=True)
    executor = EventsExecutor(context=context)
    executor.add_node(node)
    stop = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    next_report = time.time()
    while not stop.is_set():
        executor.spin_once(timeout_sec=0.05)
        now = time.time()
        if now >= next_report:
            next_report = now + 0.25
            print(f"count {now:.3f} {counts[0]} {counts[1]} {counts[2]}", flush=True)
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown(context=context)


def cpu_seconds(pid: int) -> float:
    """CPU seconds (user + system) process `pid` has used so far; NaN where /proc cannot say."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return float("nan")


class HelperDied(RuntimeError):
    """A process the ROS stage needs (a subscriber, batchsim) exited before the stage was done."""


class Helper:
    """A subscriber process of the ROS stage, its stdout for the caller to read and the last
    lines of its stderr, kept to say why it died."""

    def __init__(self, name: str, argv: list[str], env: dict[str, str]):
        self.name = name
        self.proc = subprocess.Popen(
            argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
        )
        self.stderr: deque[str] = deque(maxlen=20)
        self._stderr = threading.Thread(target=self._read_stderr, daemon=True)
        self._stderr.start()

    def _read_stderr(self) -> None:
        for line in self.proc.stderr:
            if line.strip():
                self.stderr.append(line.rstrip())

    def check(self) -> None:
        """Raise HelperDied, one line naming it and its last stderr line, if it exited."""
        if self.proc.poll() is None:
            return
        self._stderr.join(timeout=2.0)  # what it wrote before exiting
        last = self.stderr[-1] if self.stderr else "(nothing on stderr)"
        raise HelperDied(f"{self.name} (pid {self.proc.pid}) exited with status {self.proc.returncode}: {last}")


def subscriber_env() -> dict[str, str]:
    """The subscribers' environment: the checkout first on PYTHONPATH, the caller's kept after it
    (where MuJoCo or ROS is found through PYTHONPATH), as fleet.py's processes."""
    return {**os.environ, **LOCALHOST, "PYTHONPATH": _pythonpath()}


def subscriber_command(domain: int, lo: int, hi: int) -> list[str]:
    return [sys.executable, __file__, "--subscriber", str(domain), str(lo), str(hi)]


def check_batchsim(b: Batchsim) -> None:
    """Raise HelperDied if the `batchsim` process (fleet.Batchsim) exited before it was stopped."""
    if b.proc.poll() is None:
        return
    b._thread.join(timeout=2.0)
    last = next((line for _, line in reversed(b.lines) if line.strip()), "(nothing on stderr)")
    raise HelperDied(f"batchsim (pid {b.proc.pid}) exited with status {b.proc.returncode}: {last}")


def ros_row(
    backend: str, nworld: int, size: tuple[int, int], seconds: float, control: float, camera: float, lidar: float,
    workers: int | None, subscribers: int, domain: int, warmup: float | None = None, rtf: float = 0.0,
    extra: list[str] | None = None, ready_timeout: float = 300.0,
) -> dict:  # fmt: skip
    """`batchsim --rtf <rtf>` (0: flat out) with the bridge while `subscribers` processes take
    every world's image, depth and scan: the RTF it holds, what reaches the subscribers per
    wall second, and the cores each kind of process used meanwhile. A subscriber or batchsim that
    exits before the end raises HelperDied (its name and last stderr line), so no figure is made
    of what a dead process did not receive."""
    args = [
        "--model", MODEL, "--worlds", str(nworld), "--backend", backend, "--controllers", "none", "--rtf", f"{rtf:g}",
        "--control-rate", f"{control:g}", "--camera-rate", f"{camera:g}", "--lidar-rate", f"{lidar:g}",
        "--camera-resolution", f"{size[0]}x{size[1]}",
    ]  # fmt: skip
    if workers is not None:
        args += ["--bridge-workers", str(workers)]
    args += extra or []
    k = max(1, min(subscribers, nworld))
    edges = [round(i * nworld / k) for i in range(k + 1)]
    env = subscriber_env()
    helpers = [
        Helper(f"subscriber {i} (worlds {a}..{b - 1})", subscriber_command(domain, a, b), env)
        for i, (a, b) in enumerate(zip(edges[:-1], edges[1:], strict=True))
    ]
    procs = [h.proc for h in helpers]
    samples: list[list[tuple[float, tuple[int, ...]]]] = [[] for _ in procs]

    def read(i: int) -> None:
        for line in procs[i].stdout:
            parts = line.split()
            if parts and parts[0] == "count":
                samples[i].append((float(parts[1]), tuple(int(x) for x in parts[2:5])))

    for i in range(len(procs)):
        threading.Thread(target=read, args=(i,), daemon=True).start()

    def check() -> None:
        for h in helpers:
            h.check()

    def total(at: float) -> np.ndarray:
        out = np.zeros(3)
        for s in samples:
            before = [c for t, c in s if t <= at]
            out += before[-1] if before else 0
        return out

    try:
        deadline = time.time() + ready_timeout
        while not all(samples):  # each subscriber's first count line: its subscriptions made
            check()
            if time.time() > deadline:
                waiting = ", ".join(h.name for h, s in zip(helpers, samples, strict=True) if not s)
                raise HelperDied(f"{waiting}: not subscribed after {ready_timeout:g} s")
            time.sleep(0.05)
        b = Batchsim(args, domain)
        try:
            try:
                b.wait_started(300.0)
            except RuntimeError:
                check_batchsim(b)  # exited: say so in one line
                raise
            # discovery, publishers created on request, the first subscriber refresh, rendering under way
            time.sleep(warmup if warmup is not None else max(3.0, nworld / 100))
            check()
            check_batchsim(b)
            groups = {"physics": [b.proc.pid], "workers": children(b.proc.pid), "subscribers": [p.pid for p in procs]}
            cpu0 = {k: sum(cpu_seconds(pid) for pid in v) for k, v in groups.items()}
            t0 = time.time()
            c0 = total(t0)
            time.sleep(seconds)
            cpu1 = {k: sum(cpu_seconds(pid) for pid in v) for k, v in groups.items()}
            cores = {k: (cpu1[k] - cpu0[k]) / (time.time() - t0) for k in groups}
            t1 = time.time() - 0.3  # the subscribers' last reports lag a little
            c1 = total(t1)
            status = b.status(t0, t1 + 0.8)
            check()  # a subscriber that died in the window received nothing: no figure
            check_batchsim(b)
        finally:
            b.stop()
    finally:
        for p in procs:
            try:
                p.stdin.close()
            except OSError:
                pass
        for p in procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
    rtfs = [r for r, _ in status] or [float("nan")]
    got = (c1 - c0) / (t1 - t0)
    paced = rtf
    rtf = float(np.median(rtfs))
    # cpu and mjx spread a camera's worlds over whole control periods: its rate rounds to one
    rate = camera if backend == "warp" else control / max(1, round(control / camera))
    return {
        "kind": f"ROS loop {control:g} Hz + camera {camera:g} Hz + lidar {lidar:g} Hz",
        "backend": backend,
        "nworld": nworld,
        "size": f"{size[0]}x{size[1]}",
        "paced": paced,
        "rtf": rtf,
        "rtf_worst": float(min(rtfs)),
        "rtf_windows": rtfs,
        "cores": cores,
        "frames_received": float(got[0]),
        "depth_received": float(got[1]),
        "scans_received": float(got[2]),
        "frames_produced": nworld * rate * rtf,
        "scans_produced": nworld * 10.0 * rtf,  # the rover lidar's own update_rate
    }


def samples(backend: str, path: Path, nworld: int = 4) -> None:
    """A figure of `nworld` worlds: camera image, depth and the lidar scan seen from above."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sim = make(backend, 16, (320, 240))
    worlds = np.arange(nworld) * 4  # spread over the fleet: each drove its own command
    rgb, depth = sim.render(CAMERA, worlds)
    ranges = sim.scan(LIDAR, worlds)
    ld = sim.sensors.lidar(LIDAR)
    sim.shutdown()
    fig, ax = plt.subplots(3, nworld, figsize=(3.2 * nworld, 7.4), gridspec_kw={"height_ratios": [1, 1, 1.3]})
    for k, w in enumerate(worlds):
        ax[0, k].imshow(rgb[k])
        ax[0, k].set_title(f"world {w}")
        shown = np.where(np.isfinite(depth[k]), depth[k], np.nan)
        ax[1, k].imshow(shown, cmap="viridis", vmin=0, vmax=8)
        pts = ld.points(ranges[k : k + 1])[0]
        ax[2, k].scatter(pts[:, 0], pts[:, 1], s=2)
        ax[2, k].plot([0], [0], "r^")
        ax[2, k].set_aspect("equal")
        ax[2, k].set_xlim(-8, 8)
        ax[2, k].set_ylim(-8, 8)
        for a in ax[:2, k]:
            a.axis("off")
    ax[1, 0].set_title("depth, 0-8 m", loc="left", fontsize=9)
    ax[2, 0].set_title(f"{LIDAR}: {ld.nray} rays, robot frame (m)", loc="left", fontsize=9)
    fig.suptitle(f"batchsim rover, {backend} backend: RGB, depth and lidar of four worlds", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=72)


def size_arg(text: str) -> tuple[int, int]:
    w, h = text.lower().split("x")
    return int(w), int(h)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--subscriber"]:
        subscriber(*(int(a) for a in argv[1:4]))
        return 0
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--backends", default="cpu")
    p.add_argument("--worlds", default="16,256")
    p.add_argument("--sizes", default="64x64,320x240")
    p.add_argument("--seconds", type=float, default=3.0, help="per measurement, all rounds together")
    p.add_argument("--max-frames", type=int, default=300_000, help="skip camera sizes with more worlds x pixels / 1000 than this")
    p.add_argument("--no-lidar", action="store_true")
    p.add_argument("--no-camera", action="store_true")
    p.add_argument("--loop", default="", help="world counts for the loop section (e.g. 16 or 1024)")
    p.add_argument("--loop-size", default="64x64")
    p.add_argument("--loop-seconds", type=float, default=3.0, help="simulated seconds")
    p.add_argument("--control-rate", type=float, default=100.0)
    p.add_argument("--camera-rate", type=float, default=30.0)
    p.add_argument("--lidar-rate", type=float, default=10.0)
    p.add_argument("--ros", default="", help="world counts for the ROS section (with the bridge; e.g. 16 or 1024)")
    p.add_argument("--bridge-workers", type=int, default=None, help="ROS section: default batchsim's own choice")
    p.add_argument("--subscriber-processes", type=int, default=max(1, min(8, (os.cpu_count() or 2) // 2)))
    p.add_argument("--ros-seconds", type=float, default=8.0, help="ROS section: wall seconds measured")
    p.add_argument("--ros-rtf", type=float, default=0.0, help="ROS section: batchsim's --rtf (0: flat out; 1: paced at real time)")
    p.add_argument("--ros-warmup", type=float, default=None, help="ROS section: seconds from the start line to the window (default: max(3, worlds / 100))")
    p.add_argument("--ros-args", default="", help="ROS section: more arguments for batchsim (e.g. '--threads 1')")
    p.add_argument("--domain", type=int, default=72, help="ROS section: the ROS domain")
    p.add_argument("--json", default="benchmarks/out/sensors.json")
    p.add_argument("--samples", default="", help="write a figure of four worlds' images and scans here (PNG) and stop")
    args = p.parse_args(argv)
    backends = [b for b in args.backends.split(",") if b]
    if args.samples:
        samples(backends[0], Path(args.samples))
        return 0
    worlds = [int(n) for n in args.worlds.split(",") if n]
    sizes = [size_arg(s) for s in args.sizes.split(",") if s]
    header = (
        f"# {device_name(backends)} | {versions()} | {datetime.date.today()} | model {MODEL} "
        f"(camera {CAMERA}, lidar {LIDAR})"
    )
    print(header, flush=True)
    print(
        f"{'what':44s} {'backend':7s} {'worlds':>6s} {'size':>8s} {'contract/s':>12s} {'reused/s':>12s} "
        f"{'device/s':>12s} {'raw/s':>12s} {'raw graph/s':>12s} {'ratio':>6s}"
    )
    rows = []

    def show(row: dict) -> None:
        rows.append(row)

        def cell(key: str) -> str:
            value = row.get(key, float("nan"))
            return f"{value:12,.0f}" if np.isfinite(value) else " " * 12

        print(
            f"{row['kind']:44s} {row['backend']:7s} {row['nworld']:6d} {row['size']:>8s} {cell('contract_fps')} "
            f"{cell('reused_fps')} {cell('device_fps')} {cell('raw_fps')} {cell('raw_graph_fps')} {row['ratio']:6.3f}",
            flush=True,
        )

    for backend in backends:
        for n in worlds:
            if not args.no_camera:
                for size in sizes:
                    if n * size[0] * size[1] / 1000 > args.max_frames:
                        print(f"{'camera':44s} {backend:7s} {n:6d} {size[0]}x{size[1]:<4d} skipped (--max-frames)", flush=True)
                        continue
                    show(camera_row(backend, n, size, args.seconds))
            if not args.no_lidar:
                for row in lidar_rows(backend, n, args.seconds):
                    show(row)
    for backend in backends:
        for n in [int(x) for x in args.loop.split(",") if x]:
            row = loop_row(
                backend, n, size_arg(args.loop_size), args.loop_seconds, args.control_rate, args.camera_rate, args.lidar_rate
            )
            rows.append(row)
            print(
                f"{row['kind']}, {backend}, {n} worlds, {row['size']}: rtf {row['rtf']:.2f}, "
                f"{row['contract_fps']:,.0f} frames/s, {row['scans_per_s']:,.0f} scans/s, period median "
                f"{row['period_median_ms']:.2f} ms worst {row['period_worst_ms']:.2f} ms (budget {row['budget_ms']:.1f} ms)",
                flush=True,
            )
    for backend in backends:
        for n in [int(x) for x in args.ros.split(",") if x]:
            size = size_arg(args.loop_size)
            try:
                row = ros_row(
                    backend, n, size, args.ros_seconds, args.control_rate, args.camera_rate, args.lidar_rate,
                    args.bridge_workers, args.subscriber_processes, args.domain, warmup=args.ros_warmup, rtf=args.ros_rtf,
                    extra=args.ros_args.split(),
                )  # fmt: skip
            except HelperDied as e:
                print(f"sensors.py: ROS stage, {backend}, {n} worlds: {e}", file=sys.stderr, flush=True)
                return 1
            rows.append(row)
            paced = "flat out" if not row["paced"] else f"paced at rtf {row['paced']:g}"
            cores = ", ".join(f"{k} {v:.2f}" for k, v in row["cores"].items())
            print(
                f"{row['kind']}, {backend}, {n} worlds, {row['size']}, with ROS publishing ({paced}): rtf {row['rtf']:.2f} "
                f"(worst {row['rtf_worst']:.2f}), received {row['frames_received']:,.0f} frames/s + "
                f"{row['depth_received']:,.0f} depth/s + {row['scans_received']:,.0f} scans/s "
                f"(produced {row['frames_produced']:,.0f} frames/s, {row['scans_produced']:,.0f} scans/s); "
                f"cores used: {cores}",
                flush=True,
            )
    write_json(Path(args.json), {"header": header, "rows": rows})
    return 0


def json_value(value):
    """`value` as strict JSON takes it: NaN and infinities (no value: a column a backend lacks, a
    window /proc could not measure) become null, numpy scalars Python ones, containers recursively."""
    if isinstance(value, dict):
        return {str(k): json_value(v) for k, v in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [json_value(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def write_json(path: Path, document: dict) -> None:
    """Write `document` to `path` as valid JSON (no NaN or Infinity tokens)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(json_value(document), indent=1, allow_nan=False))


if __name__ == "__main__":
    sys.exit(main())
