"""The fleet's web view: `python -m ros_bridge.worker.view STATUS_FD` (ros_bridge/view_plan.py
starts it with the bridge and hands it the plan on standard input).

A viser server (a local web page, three.js in the browser, served by this process) shows
every world in a grid, drawn from MuJoCo's own geometry: each visible geom is one instanced
mesh with an instance per world, so a thousand worlds cost the browser one draw call per geom
and this process one array per geom per update. Each world is tinted by its status (red:
frozen, diverged or overflowed; orange: its last command was rejected; yellow: command
timeout); the panel shows sim time, the RTF and how many worlds are in each state; a world is
picked by its number or by clicking it, and the panel then shows its status, its joint
positions over the last seconds and, where the fleet has cameras, its camera's latest RGB
image (the first camera, or the one chosen). Poses and status come from the snapshot the
bridge workers read (ros_bridge/protocol/snapshot.py), at most UPDATE_RATE times a second;
the image from the camera's sensor block (ros_bridge/protocol/sensor_blocks.py), rendered
for that one world while the view asks (`view.camera`, ros_bridge/view_plan.py's ViewCamera).

viser rather than foxglove-sdk or rerun: it serves its own page from this process (no app to
fetch from the internet, so a browser on an isolated machine works), instanced meshes with a
colour per instance are part of its API, and its panel (numbers, text, plots) is enough for
the picked world.
"""

from __future__ import annotations

import collections
import contextlib
import io
import os
import pickle
import signal
import sys
import time as wallclock
from typing import Any

import numpy as np
import viser

from batchsim.memory import Memory
from batchsim.types import FROZEN, Status
from ros_bridge.plan import FLAG_BAD, FLAG_FROZEN, FLAG_TIMED_OUT, FleetPlan
from ros_bridge.protocol.demand import ChannelDemand
from ros_bridge.protocol.sensor_blocks import WANT_RGB, CameraRequest, SensorBlock
from ros_bridge.protocol.snapshot import Snapshot, read_snapshot
from ros_bridge.view_plan import ViewSpec
from ros_bridge.worker.process import die_with_parent
from ros_bridge.world_status import status_text

UPDATE_RATE = 20.0  # Hz
PLOT_SECONDS = 10.0
NICE = 10
FROZEN_RGB, BAD_RGB, TIMEOUT_RGB = (220, 30, 30), (255, 140, 0), (240, 220, 0)
NO_IMAGE = 40  # the image's grey until the picked world's camera sends a frame


def qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products of (..., 4) quaternions (w, x, y, z)."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([
        aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw,
    ], -1)  # fmt: skip


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(..., 3) vectors v rotated by (..., 4) quaternions q."""
    u, w = q[..., 1:], q[..., :1]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


class FleetScene:
    """The page: `spec`'s geoms for `nworld` worlds (named `namespaces`) on a grid, the panel's
    fleet line, its world picker and status line, the picked world's joint plot and, where
    `cameras` ((name, height, width) each) are given, its camera image and camera chooser."""

    def __init__(self, spec: ViewSpec, namespaces: list[str], cameras: tuple[tuple[str, int, int], ...] = ()):
        self.spec, self.namespaces = spec, namespaces
        self.n = n = len(namespaces)
        cols = int(np.ceil(np.sqrt(n)))
        k = np.arange(n)
        self.grid = np.stack([(k % cols) * spec.spacing, (k // cols) * spec.spacing, np.zeros(n)], -1)
        with contextlib.redirect_stdout(io.StringIO()):  # its banner: batchsim prints the URL itself
            self.server = viser.ViserServer(host=spec.host, port=spec.port, label="batchsim", verbose=False)
        scene, gui = self.server.scene, self.server.gui
        center = np.array([self.grid[:, 0].max() / 2, self.grid[:, 1].max() / 2, 0.0])
        reach = max(center[0], 1.0) + spec.spacing  # the whole grid in sight
        self.server.initial_camera.look_at = tuple(center)
        self.server.initial_camera.position = tuple(center + np.array([-0.7, -0.9, 0.6]) * reach)
        self.server.initial_camera.up = (0.0, 0.0, 1.0)
        scene.add_grid("/floor", width=cols * spec.spacing + spec.spacing, height=cols * spec.spacing + spec.spacing,
                       cell_size=spec.spacing / 4, section_size=spec.spacing, position=tuple(center))  # fmt: skip
        self.base_rgb = [np.clip(g.rgba[:3] * 255, 0, 255).astype(np.uint8) for g in spec.geoms]
        self.handles = []
        for i, g in enumerate(spec.geoms):
            handle = scene.add_batched_meshes_simple(
                f"/fleet/{i}_{g.name}", g.vertices, g.faces,
                batched_wxyzs=np.tile(g.quat, (n, 1)).astype(np.float32),
                batched_positions=(self.grid + g.pos).astype(np.float32),
                batched_colors=np.tile(self.base_rgb[i], (n, 1)),
            )  # fmt: skip
            handle.on_click(self._clicked)
            self.handles.append(handle)
        self.fleet_text = gui.add_markdown("starting ...")
        self.picker = gui.add_number("world", 0, min=0, max=max(0, n - 1), step=1)
        self.world_text = gui.add_markdown("")
        self.plot: Any = None
        if spec.joints is not None:
            names = spec.joints[2]
            series = (viser.uplot.Series(label="t"), *(viser.uplot.Series(label=j, stroke=_stroke(i)) for i, j in enumerate(names)))
            self.plot = gui.add_uplot(data=(np.zeros(1), *[np.zeros(1)] * len(names)), series=series,
                                      title="joint positions (rad, m) against sim time (s)",
                                      scales={"x": {"time": False}}, aspect=1.5)  # fmt: skip
        self.cameras = cameras
        self.chooser: Any = None
        self.image: Any = None
        if len(cameras) > 1:
            self.chooser = gui.add_dropdown("camera", tuple(c[0] for c in cameras), initial_value=cameras[0][0])
        if cameras:
            self.image = gui.add_image(self.blank(0), label=cameras[0][0], format="jpeg", jpeg_quality=85)
        self._colors_key: bytes = b""
        self.url = f"http://{'localhost' if spec.host in ('0.0.0.0', '127.0.0.1') else spec.host}:{self.server.get_port()}"

    @property
    def picked(self) -> int:
        return int(np.clip(self.picker.value, 0, self.n - 1))

    @property
    def camera(self) -> int:
        """The chosen camera's index in `cameras` (0 without a chooser)."""
        names = [c[0] for c in self.cameras]
        return names.index(self.chooser.value) if self.chooser is not None else 0

    def blank(self, camera: int) -> np.ndarray:
        _name, h, w = self.cameras[camera]
        return np.full((h, w, 3), NO_IMAGE, np.uint8)

    def _clicked(self, event: Any) -> None:
        if event.instance_index is not None:
            self.picker.value = int(event.instance_index)

    def draw(self, poses: np.ndarray) -> None:
        """poses: (nworld, nanchor, 7) the anchors' world poses (position, quaternion w x y z)."""
        with self.server.atomic():
            for g, handle in zip(self.spec.geoms, self.handles, strict=True):
                if g.anchor < 0:
                    continue  # on the world body: never moves
                p, q = poses[:, g.anchor, :3], poses[:, g.anchor, 3:]
                handle.batched_positions = (self.grid + p + rotate(q, np.broadcast_to(g.pos, p.shape))).astype(np.float32)
                handle.batched_wxyzs = qmul(q, np.broadcast_to(g.quat, q.shape)).astype(np.float32)

    def tint(self, status: np.ndarray, flags: np.ndarray) -> None:
        key = status.tobytes() + flags.tobytes()
        if key == self._colors_key:
            return
        self._colors_key = key
        frozen = ((flags & FLAG_FROZEN) != 0) | ((status & int(FROZEN)) != 0)
        bad = ((flags & FLAG_BAD) != 0) | ((status & int(Status.BAD_COMMAND)) != 0)
        timeout = (flags & FLAG_TIMED_OUT) != 0
        for rgb, handle in zip(self.base_rgb, self.handles, strict=True):
            colors = np.tile(rgb, (self.n, 1))
            colors[timeout] = TIMEOUT_RGB
            colors[bad] = BAD_RGB
            colors[frozen] = FROZEN_RGB
            handle.batched_colors = colors

    def plot_joints(self, t: np.ndarray, q: np.ndarray) -> None:
        """The picked world's joint positions q (len(t), njoint) at sim times t."""
        if self.plot is not None and len(t):
            self.plot.data = (t, *q.reshape(len(t), -1).T)


class FleetView:
    """The live page for `plan`'s worlds, fed from `memory` (the snapshot)."""

    def __init__(self, plan: FleetPlan, memory: Memory):
        self.plan, self.spec, self.memory = plan, plan.view, memory
        self.n = plan.nworld
        self.snap = Snapshot()
        self.rtf = collections.deque(maxlen=int(UPDATE_RATE))  # (wall, sim) of the last second
        cameras = plan.sensors.cameras if plan.sensors is not None else ()
        self.scene = FleetScene(plan.view, plan.namespaces, tuple((c.camera.name, c.camera.height, c.camera.width) for c in cameras))
        self.url = self.scene.url
        self.history: collections.deque = collections.deque()
        self.scene.picker.on_update(lambda _: self.history.clear())
        self.blocks = [SensorBlock(memory, f"cam{k}", ("rgb",)) for k in range(len(cameras))]
        self.camera = CameraRequest(memory) if self.blocks else None  # the image the loop renders for us
        self.seen = np.full(1, -1, np.int64)  # the seq of the shown world's frame last taken
        self.shown = (-1, -1)  # (world, camera) of the image

    def want(self, on: bool) -> None:
        """Ask the loop for the channels the view reads (the tf poses, the joint positions);
        off, for no camera image either."""
        want = ChannelDemand(self.memory, "view.want")
        if on:
            want.set([self.spec.channel] + ([self.spec.joints[0]] if self.spec.joints is not None else []))
        else:
            want.clear()
        if not on and self.blocks:
            self.camera.clear()
            self.shown = (-1, -1)

    def update(self) -> None:
        snap = read_snapshot(self.memory, len(self.plan.channels), 0, self.n, self.snap)
        if snap is None:
            return
        self.rtf.append((wallclock.monotonic(), snap.time))
        if self.spec.channel in snap.channels:
            self.scene.draw(snap.channels[self.spec.channel].reshape(self.n, -1, 7))
        self.scene.tint(snap.status, snap.flags)
        self._panel(snap)
        if self.blocks:
            self._image()

    def _image(self) -> None:
        """The picked world's newest frame of the chosen camera, asked for while it is shown."""
        w, k = self.scene.picked, self.scene.camera
        block = self.blocks[k]
        if (w, k) != self.shown:  # only frames rendered from now: an older one may be long stale
            self.camera.ask(w, k)
            self.shown = (w, k)
            self.seen[0] = block.seq[w]
            self.scene.image.image = self.scene.blank(k)
            self.scene.image.label = f"{self.scene.cameras[k][0]} (world {w})"
        rows, parts, _time, data = block.read_worlds(np.array([w]), self.seen)
        if rows.size and parts[0] & WANT_RGB:
            self.scene.image.image = data["rgb"][0]

    def _panel(self, snap: Snapshot) -> None:
        (w0, s0), (w1, s1) = self.rtf[0], self.rtf[-1]
        rtf = (s1 - s0) / (w1 - w0) if w1 > w0 else 0.0
        frozen = int(((snap.flags & FLAG_FROZEN) != 0).sum())
        bad = int(((snap.flags & FLAG_BAD) != 0).sum())
        timeout = int(((snap.flags & FLAG_TIMED_OUT) != 0).sum())
        self.scene.fleet_text.content = (
            f"**{self.n} worlds** · sim time {snap.time:.2f} s · RTF {rtf:.2f}  \n"
            f"running {self.n - frozen} · frozen {frozen} · bad command {bad} · command timeout {timeout}"
        )
        w = self.scene.picked
        self.scene.world_text.content = f"**{self.plan.namespaces[w] or '/'}** (world {w}): {status_text(int(snap.status[w]), int(snap.flags[w]))}"
        joints = self.spec.joints
        if joints is not None and joints[0] in snap.channels:
            self.history.append((snap.time, snap.channels[joints[0]][w, list(joints[1])]))
            while self.history and self.history[0][0] < snap.time - PLOT_SECONDS:
                self.history.popleft()
            self.scene.plot_joints(np.array([h[0] for h in self.history]), np.array([h[1] for h in self.history]))


def _stroke(i: int) -> str:
    return ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f")[i % 8]


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    status = os.fdopen(int(argv[0]), "w", buffering=1)
    die_with_parent()
    os.nice(NICE)  # the loop and the workers come first for the cores
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the physics process, which stops us
    stopping: list[int] = []
    signal.signal(signal.SIGTERM, lambda signum, frame: stopping.append(signum))
    try:
        plan: FleetPlan = pickle.load(sys.stdin.buffer)
    except (EOFError, pickle.UnpicklingError):
        return 0
    memory = Memory.attach(plan.layout, plan.memory_name)
    try:
        view = FleetView(plan, memory)
    except OSError as e:  # the port is taken, the address is not this host's
        status.write(f"warning: view: cannot serve on {plan.view.host}:{plan.view.port}: {e.strerror or e}; the simulation goes on\n")
        return 1
    view.want(True)
    status.write(f"ready {view.url}\n")
    try:
        while not stopping:
            began = wallclock.monotonic()
            view.update()
            wallclock.sleep(max(0.0, 1.0 / UPDATE_RATE - (wallclock.monotonic() - began)))
    finally:
        view.want(False)
        view.scene.server.stop()
        memory.close()
    return 0


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    os._exit(code)
