"""The fleet's web view, as data and as a process: what it draws (`ViewSpec`, from MuJoCo's own
geometry) and the physics side (`ViewProcess`). No rclpy, no web code here.

The view (ros_bridge/worker/view.py) is a process of its own, as the recorder is, so serving
the page and its updates never takes the loop's interpreter. It reads the snapshot the bridge
workers read: each world's status and flags, and the tf channel's body poses (the moving
frames' ends, tf_plan.py), from which every visible geom's pose follows by a fixed offset
computed here once. So the view costs the loop only the tf channel's copy, which it asks
for through `view.want` while it runs. Where the fleet has cameras, each browser's panel shows
its picked world's camera image: the view process writes the distinct (world, camera) pairs
its browsers show into `view.camera` (up to MAX_VIEW_CAMERAS), and the physics side
(`ViewCamera`, asked by sensor_topics.py's SensorFeed) ORs WANT_RGB into those worlds' want
bits, so those cameras render as if subscribed; the view reads their blocks.

A fleet of several groups of worlds (batchsim.fleet.groups) is one view: each group's bridge
has its own plan (its own ViewSpec: its robots' geoms) and shared memory, and one view process
reads them all (`ViewProcess` takes every group's plan), drawing each world with its group's
geoms at its place in the fleet's grid.
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import pickle
import select
import subprocess
import sys
import time as wallclock

import mujoco
import numpy as np

from batchsim.contract import Contract
from batchsim.model.frames import frame_tree
from ros_bridge.protocol.sensor_blocks import WANT_RGB, CameraRequest
from ros_bridge.throttle import how_ended

GEOMETRY = "batchsim/view_geometry.npz"  # a recording's attachment: the robots' geoms (`batchsim view FILE`)
VISIBLE_GROUPS = 3  # MuJoCo's viewer shows geom groups 0, 1 and 2 by default
READY_TIMEOUT = 60.0  # s the view process may take to come up
_G = mujoco.mjtGeom


@dataclasses.dataclass(frozen=True)
class ViewGeom:
    """One visible geom: `anchor`, the index of the tf channel body it moves with (-1: the
    world); `pos`, `quat` (w, x, y, z), its pose in the anchor's frame; `rgba`; its triangle
    mesh, `vertices` (nv, 3) float32 and `faces` (nf, 3) uint32, in its own frame."""

    name: str
    anchor: int
    pos: np.ndarray
    quat: np.ndarray
    rgba: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray


@dataclasses.dataclass(frozen=True)
class ViewSpec:
    """What the view draws: `geoms`; `channel`, the tf channel (7 values per body: position,
    quaternion w x y z); `spacing`, metres between two worlds of the grid; `host`, `port`,
    where the page is served; `joints`: the joint_states output's channel and position columns
    (for the picked world's plot), or None."""

    geoms: tuple[ViewGeom, ...]
    channel: int
    spacing: float
    host: str
    port: int
    joints: tuple[int, tuple[int, ...], tuple[str, ...]] | None = None


def _sphere(n: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """A unit UV sphere: (vertices, faces)."""
    theta = np.linspace(0, np.pi, n + 1)
    phi = np.linspace(0, 2 * np.pi, 2 * n, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    v = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    m = 2 * n
    faces = []
    for i in range(n):
        for j in range(m):
            a, b, c, d = i * m + j, i * m + (j + 1) % m, (i + 1) * m + j, (i + 1) * m + (j + 1) % m
            faces += [(a, c, b), (b, c, d)]
    return v, np.array(faces)


def _cylinder(n: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """A cylinder of radius 1 from z=-1 to z=1, capped: (vertices, faces)."""
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([np.cos(a), np.sin(a)], -1)
    v = np.concatenate([np.c_[ring, -np.ones(n)], np.c_[ring, np.ones(n)], [[0, 0, -1], [0, 0, 1]]])
    faces = []
    for j in range(n):
        k = (j + 1) % n
        faces += [(j, k, n + j), (k, n + k, n + j), (2 * n, k, j), (2 * n + 1, n + j, n + k)]
    return v, np.array(faces)


_BOX_V = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
_BOX_F = np.array([
    (0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1),
    (2, 3, 7), (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3),
])  # fmt: skip


def geom_mesh(m: mujoco.MjModel, g: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Geom g's triangles in its own frame, or None for what the view leaves out (planes, height fields)."""
    kind, size = int(m.geom_type[g]), m.geom_size[g]
    if kind == _G.mjGEOM_MESH:
        mesh = int(m.geom_dataid[g])
        v0, nv = int(m.mesh_vertadr[mesh]), int(m.mesh_vertnum[mesh])
        f0, nf = int(m.mesh_faceadr[mesh]), int(m.mesh_facenum[mesh])
        return m.mesh_vert[v0 : v0 + nv].copy(), m.mesh_face[f0 : f0 + nf].copy()
    if kind == _G.mjGEOM_BOX:
        return _BOX_V * size, _BOX_F
    if kind in (_G.mjGEOM_SPHERE, _G.mjGEOM_ELLIPSOID):
        v, f = _sphere()
        return v * (size[:3] if kind == _G.mjGEOM_ELLIPSOID else size[0]), f
    if kind == _G.mjGEOM_CAPSULE:  # a sphere whose halves move apart by the half-length
        v, f = _sphere()
        v = v * size[0]
        v[:, 2] += np.where(v[:, 2] >= 0, size[1], -size[1])
        return v, f
    if kind == _G.mjGEOM_CYLINDER:
        v, f = _cylinder()
        return v * np.array([size[0], size[0], size[1]]), f
    return None


def _pose_in(m: mujoco.MjModel, body: int, anchors: set[int]) -> tuple[int, np.ndarray, np.ndarray]:
    """The nearest ancestor of `body` (itself included) among `anchors` (0: the world), and
    `body`'s fixed pose in its frame (the bodies between have no joint)."""
    pos, quat = np.zeros(3), np.array([1.0, 0, 0, 0])
    while body not in anchors and body != 0:
        p, q = np.zeros(3), np.zeros(4)
        mujoco.mju_mulPose(p, q, m.body_pos[body], m.body_quat[body], pos, quat)
        pos, quat, body = p, q, int(m.body_parentid[body])
    return body, pos, quat


def view_spec(sim: Contract, tf_channel: int, tf_bodies: tuple[int, ...], host: str, port: int,
              joints: tuple[int, tuple[int, ...], tuple[str, ...]] | None = None) -> ViewSpec:  # fmt: skip
    """The visible geoms of `sim`'s model, each anchored to a body of the tf channel (`tf_bodies`, its body ids)."""
    m = sim.model
    index = {b: k for k, b in enumerate(tf_bodies)}
    geoms = []
    for g in range(m.ngeom):
        if m.geom_group[g] >= VISIBLE_GROUPS or m.geom_rgba[g, 3] == 0:
            continue
        mesh = geom_mesh(m, g)
        if mesh is None:
            continue
        body, pos, quat = _pose_in(m, int(m.geom_bodyid[g]), set(index))
        p, q = np.zeros(3), np.zeros(4)
        mujoco.mju_mulPose(p, q, pos, quat, m.geom_pos[g], m.geom_quat[g])
        mat = int(m.geom_matid[g])
        rgba = m.mat_rgba[mat] if mat >= 0 else m.geom_rgba[g]
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom_{g}"
        geoms.append(ViewGeom(name, index.get(body, -1), p, q, rgba.copy(), mesh[0].astype(np.float32), mesh[1].astype(np.uint32)))
    spacing = max(1.0, 2.5 * float(m.stat.extent))
    return ViewSpec(tuple(geoms), tf_channel, spacing, host, port, joints)


def geometry_bytes(spec: ViewSpec, anchor_frames: list[str]) -> bytes:
    """The geoms of `spec` and the tf frames of its anchors, as an .npz (no pickle): what a
    recording carries (an MCAP attachment) so that `batchsim view FILE` draws its robots."""
    arrays: dict[str, np.ndarray] = {
        "names": np.array(json.dumps([g.name for g in spec.geoms])),
        "frames": np.array(json.dumps(anchor_frames)),
        "anchor": np.array([g.anchor for g in spec.geoms], np.int64),
        "pos": np.array([g.pos for g in spec.geoms]).reshape(-1, 3),
        "quat": np.array([g.quat for g in spec.geoms]).reshape(-1, 4),
        "rgba": np.array([g.rgba for g in spec.geoms]).reshape(-1, 4),
        "spacing": np.array(spec.spacing),
    }
    for k, g in enumerate(spec.geoms):
        arrays[f"v{k}"], arrays[f"f{k}"] = g.vertices, g.faces
    out = io.BytesIO()
    np.savez_compressed(out, **arrays)
    return out.getvalue()


def geometry_from_bytes(data: bytes, host: str, port: int) -> tuple[ViewSpec, list[str]]:
    """`geometry_bytes` read back: the ViewSpec (served at host:port) and the anchors' tf frames."""
    z = np.load(io.BytesIO(data), allow_pickle=False)
    names = json.loads(str(z["names"]))
    geoms = tuple(
        ViewGeom(name, int(z["anchor"][k]), z["pos"][k], z["quat"][k], z["rgba"][k], z[f"v{k}"], z[f"f{k}"])
        for k, name in enumerate(names)
    )
    return ViewSpec(geoms, -1, float(z["spacing"]), host, port), json.loads(str(z["frames"]))


def geometry_attachment(group: str | None = None) -> str:
    """The name of a recording's geometry attachment: GEOMETRY for a fleet of one group; in a
    fleet of several, each group's own (`batchsim/view_geometry.<group>.npz`), which the file's
    `batchsim` metadata names beside the group's worlds."""
    if not group:
        return GEOMETRY
    stem, suffix = GEOMETRY.rsplit(".", 1)
    return f"{stem}.{group}.{suffix}"


def recording_geometry(sim: Contract, tf) -> bytes:
    """What a recording of `sim` carries for the view: its geoms, anchored to tf's frames."""
    tree = frame_tree(sim.spec)
    return geometry_bytes(view_spec(sim, tf.channel, tf.bodies, "", 0), [tree.frame(b) for b in tf.bodies])


class ViewCamera:
    """The physics side of the view's camera images: the view process's request
    (protocol/sensor_blocks.py's CameraRequest: the (world, camera) pairs its browsers show, up
    to MAX_VIEW_CAMERAS) becomes WANT_RGB in each pair's world's camera column of the want bits,
    so each camera renders once for every world asked of it."""

    def __init__(self, memory) -> None:
        self.request = CameraRequest(memory)
        self.request.clear()  # nothing until the page asks (a new segment reads as world 0)

    def want_sensors(self, want: np.ndarray) -> None:
        """OR the view's cameras into `want` ((nworld, nsensor), the workers' want bits)."""
        for world, camera in self.request.asked():
            if world < want.shape[0] and camera < want.shape[1]:
                want[world, camera] |= WANT_RGB


def view_camera(memory) -> ViewCamera | None:
    """The view's camera request in `memory` (a bridge's shared arrays), where its fleet has cameras."""
    return ViewCamera(memory) if memory is not None and "view.camera" in memory else None


class ViewProcess:
    """The view's process: started with the bridge, stopped with it; its URL once it serves.

    Args:
      plans: the plan of the bridge whose worlds it shows; in a fleet of several groups, every
        group's, the first group's first (its ViewSpec says where the page is served).
      cameras: the bridges' camera requests (`view_camera`), cleared when the view closes.
    """

    def __init__(self, plans, cameras=()) -> None:
        self.cameras = [c for c in cameras if c is not None]
        self._closed = self._said_ended = False
        self._next_watch = 0.0
        read, write = os.pipe()
        self._proc = subprocess.Popen(  # stdout: viser's banner, which the URL line below replaces
            [sys.executable, "-m", "ros_bridge.worker.view", str(write)], stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, pass_fds=(write,)
        )
        os.close(write)
        self._proc.stdin.write(pickle.dumps(list(plans)))
        self._proc.stdin.close()
        self._status = os.fdopen(read, "r")
        self.url: str | None = None
        deadline = wallclock.monotonic() + READY_TIMEOUT
        while self.url is None and wallclock.monotonic() < deadline and self._proc.poll() is None:
            if select.select([self._status], [], [], 0.2)[0]:
                line = self._status.readline().strip()
                if line.startswith("ready "):
                    self.url = line.split(" ", 1)[1]
                elif line:
                    print(f"batchsim: {line}", file=sys.stderr, flush=True)

    def watch(self) -> None:
        """One of the supervisor's watchers (at most once a second): a view process that ended
        while the fleet runs is said once, with how it ended; the simulation goes on."""
        now = wallclock.monotonic()
        if self._closed or self._said_ended or now < self._next_watch:
            return
        self._next_watch = now + 1.0
        code = self._proc.poll()
        if code is not None:
            self._said_ended = True
            for camera in self.cameras:
                camera.request.clear()
            print(f"batchsim: warning: view: its process {how_ended(code)}; the page no longer updates, the simulation goes on",
                  file=sys.stderr, flush=True)  # fmt: skip

    def close(self) -> None:
        """Stop the process; the camera requests cleared. Safe to call twice (each group's bridge does)."""
        if self._closed:
            return
        self._closed = True
        for camera in self.cameras:
            camera.request.clear()
        if self._proc.poll() is None:
            self._proc.terminate()
            try:
                self._proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self._proc.kill()
        self._status.close()
