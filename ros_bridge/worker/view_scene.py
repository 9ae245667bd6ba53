"""The web view's page (`FleetScene`): the worlds on one grid, drawn from MuJoCo's own geometry,
and the panel. The live view (view.py) and a recording's (ros_bridge/view_file.py) fill it.

A viser server (a local web page, three.js in the browser, served by this process) shows every
world in a grid: each visible geom is one instanced mesh with an instance per world, so a
thousand worlds cost the browser one draw call per geom and this process one array per geom per
update. Each world is tinted by its status: frozen (diverged or overflowed), its last command
rejected, or a command timeout, each tint picked from a few candidates as the one farthest from
every robot colour of the scene (`tints`), and the panel's legend names them. The first view
frames every world of the grid. The worlds, their tints, the floor, the worlds' numbers (in a
fleet of up to LABELLED worlds) and the panel's fleet line and legend are the page's, the same
in every browser.

Each browser (a viser client) keeps its own pick (`Pick`, made when it connects, forgotten when
it leaves): a world is picked by its number or by clicking it in that browser, and only that
browser sees the box that marks its cell, the label that names it, and its panel: its status,
its joint positions over the last seconds and, where its worlds have cameras, its camera's
latest RGB image (the first camera, or the one chosen).

A fleet of several groups of worlds (batchsim.fleet.groups) is one scene of several parts
(`ScenePart`): each group's worlds are drawn with its own robots' geoms at their places in the
one grid (the fleet's numbering), and a pick's plot and camera are its world's group's.
No rclpy here: `batchsim view FILE` runs where ROS 2 is not installed.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import io
import threading
from collections.abc import Sequence
from typing import Any

import numpy as np
import viser

from batchsim.types import FROZEN, Status
from ros_bridge.plan import FLAG_BAD, FLAG_FROZEN, FLAG_TIMED_OUT
from ros_bridge.view_plan import ViewSpec
from ros_bridge.worker import view_server

# per status, the tints it may take (name, rgb), the first of those farthest from the robots' colours
TINT_CANDIDATES = {
    "frozen": (("red", (220, 30, 30)), ("magenta", (230, 0, 200)), ("purple", (120, 0, 220))),
    "bad command": (("magenta", (230, 0, 200)), ("cyan", (0, 200, 230)), ("orange", (255, 140, 0))),
    "command timeout": (("yellow", (240, 220, 0)), ("lime", (120, 255, 0)), ("white", (255, 255, 255))),
}
HIGHLIGHT_RGB = (0, 160, 255)  # the picked world's box
LABELLED = 64  # up to this many worlds, each is labelled with its number
NO_IMAGE = 40  # the image's grey until the picked world's camera sends a frame
# the panel's order, top down, whichever scope made each (the page's elements, a browser's)
ORDER = {"fleet": 1.0, "tints": 2.0, "world": 3.0, "status": 4.0, "plot": 5.0, "camera": 6.0, "image": 7.0}
CONTROLS_ORDER = 10.0  # a view's own controls, below the panel (the recording's slider, then `play`)


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


@dataclasses.dataclass(frozen=True)
class ScenePart:
    """One group's worlds in the scene (a fleet of one group: every world): `spec`, what its
    worlds draw (their geoms, the joint plot's names); `worlds`, their indices among the scene's
    worlds, in order; `cameras`, (name, height, width) of each camera its worlds have."""

    spec: ViewSpec
    worlds: tuple[int, ...]
    cameras: tuple[tuple[str, int, int], ...] = ()


class FleetScene:
    """The page: the worlds named `namespaces` on one grid, each drawn with its part's geoms
    (`parts`: one per group, each world in one; the first part's spec says where the page is
    served), the panel's fleet line and tint legend; and each connected browser's `Pick`
    (`picks`), its world picker, status line, joint plot and camera image."""

    def __init__(self, parts: Sequence[ScenePart], namespaces: list[str]):
        self.parts, self.namespaces = list(parts), namespaces
        self.n = n = len(namespaces)
        self.part_of = np.zeros(n, np.intp)  # per world: its part, and its index among the part's worlds
        self.row_of = np.zeros(n, np.intp)
        for k, part in enumerate(self.parts):
            self.part_of[list(part.worlds)] = k
            self.row_of[list(part.worlds)] = np.arange(len(part.worlds))
        spec = self.parts[0].spec
        spacing = max(p.spec.spacing for p in self.parts)
        cols = int(np.ceil(np.sqrt(n)))
        k = np.arange(n)
        self.grid = np.stack([(k % cols) * spacing, (k // cols) * spacing, np.zeros(n)], -1)
        with contextlib.redirect_stdout(io.StringIO()):  # its banner: batchsim prints the URL itself
            self.server = view_server.serve(spec.host, spec.port, label="batchsim", verbose=False)
        scene, gui = self.server.scene, self.server.gui
        position, center = framing(self.grid, spacing, self.server.initial_camera.fov)
        self.server.initial_camera.look_at = tuple(center)
        self.server.initial_camera.position = tuple(position)
        self.server.initial_camera.up = (0.0, 0.0, 1.0)
        scene.add_grid("/floor", width=cols * spacing + spacing, height=cols * spacing + spacing,
                       cell_size=spacing / 4, section_size=spacing, position=tuple(center))  # fmt: skip
        self.base_rgb: list[list[np.ndarray]] = []  # per part, per geom
        self.handles: list[list[Any]] = []
        for p, part in enumerate(self.parts):
            grid, m = self.grid[list(part.worlds)], len(part.worlds)
            path = "/fleet" if len(self.parts) == 1 else f"/fleet/{p}"
            self.base_rgb.append([np.clip(g.rgba[:3] * 255, 0, 255).astype(np.uint8) for g in part.spec.geoms])
            self.handles.append([])
            for i, g in enumerate(part.spec.geoms):
                handle = scene.add_batched_meshes_simple(
                    f"{path}/{i}_{g.name}", g.vertices, g.faces,
                    batched_wxyzs=np.tile(g.quat, (m, 1)).astype(np.float32),
                    batched_positions=(grid + g.pos).astype(np.float32),
                    batched_colors=np.tile(self.base_rgb[p][i], (m, 1)),
                )  # fmt: skip
                handle.on_click(lambda event, part=part: self._clicked(part, event))
                self.handles[p].append(handle)
        self.tints = tints([rgb for rgbs in self.base_rgb for rgb in rgbs])
        self.spacing = spacing
        if n <= LABELLED:
            for w in range(n):
                scene.add_label(f"/labels/{w}", str(w), position=tuple(self.grid[w] + (-0.4 * spacing, -0.4 * spacing, 0.0)))
        self.fleet_text = gui.add_markdown("starting ...", order=ORDER["fleet"])
        legend = " · ".join(f"{name}: {state}" for state, (name, _) in self.tints.items())
        self.tint_text = gui.add_markdown("tints: " + legend, order=ORDER["tints"])
        self.cameras_shown = any(p.cameras for p in self.parts)  # whether a pick's panel has a camera image
        self._picks: dict[int, Pick] = {}  # per connected browser (its client id), its pick
        self._lock = threading.Lock()
        self.server.on_client_connect(self._joined)
        self.server.on_client_disconnect(self._left)
        self._colors_key: bytes = b""
        self.url = f"http://{'localhost' if spec.host in ('0.0.0.0', '127.0.0.1') else spec.host}:{self.server.get_port()}"

    def picks(self) -> list[Pick]:
        """Every connected browser's pick, the first connected first."""
        with self._lock:
            return [self._picks[c] for c in sorted(self._picks)]

    def pick_of(self, client_id: int) -> Pick | None:
        """The pick of the browser whose viser client id is `client_id` (None once it left)."""
        with self._lock:
            return self._picks.get(client_id)

    def _joined(self, client: viser.ClientHandle) -> None:
        pick = Pick(self, client)
        with self._lock:
            self._picks[client.client_id] = pick
        if client.client_id not in self.server.get_clients():  # it left while its panel was made
            self._left(client)

    def _left(self, client: viser.ClientHandle) -> None:
        with self._lock:
            self._picks.pop(client.client_id, None)

    def _clicked(self, part: ScenePart, event: Any) -> None:
        """A click on a world picks it in the browser that clicked."""
        pick = self.pick_of(event.client_id)
        if pick is not None and event.instance_index is not None:
            pick.pick(int(part.worlds[int(event.instance_index)]))

    def draw(self, poses: np.ndarray, part: int = 0) -> None:
        """poses: (nworld, nanchor, 7) the anchors' world poses (position, quaternion w x y z) of
        part `part`'s worlds (every world, for one part)."""
        grid = self.grid[list(self.parts[part].worlds)]
        with self.server.atomic():
            for g, handle in zip(self.parts[part].spec.geoms, self.handles[part], strict=True):
                if g.anchor < 0:
                    continue  # on the world body: never moves
                p, q = poses[:, g.anchor, :3], poses[:, g.anchor, 3:]
                handle.batched_positions = (grid + p + rotate(q, np.broadcast_to(g.pos, p.shape))).astype(np.float32)
                handle.batched_wxyzs = qmul(q, np.broadcast_to(g.quat, q.shape)).astype(np.float32)

    def tint(self, status: np.ndarray, flags: np.ndarray) -> None:
        """Every world's colour from its status bits and flags ((nworld,) each)."""
        key = status.tobytes() + flags.tobytes()
        if key == self._colors_key:
            return
        self._colors_key = key
        frozen = ((flags & FLAG_FROZEN) != 0) | ((status & int(FROZEN)) != 0)
        bad = ((flags & FLAG_BAD) != 0) | ((status & int(Status.BAD_COMMAND)) != 0)
        timeout = (flags & FLAG_TIMED_OUT) != 0
        tint = {state: rgb for state, (_, rgb) in self.tints.items()}
        for part, rgbs, handles in zip(self.parts, self.base_rgb, self.handles, strict=True):
            rows = list(part.worlds)
            for rgb, handle in zip(rgbs, handles, strict=True):
                colors = np.tile(rgb, (len(rows), 1))
                colors[timeout[rows]] = tint["command timeout"]
                colors[bad[rows]] = tint["bad command"]
                colors[frozen[rows]] = tint["frozen"]
                handle.batched_colors = colors


class Pick:
    """One browser's pick and its part of the panel, made in that browser only (viser's
    `client.gui` and `client.scene`: no other browser sees them): the world picker, the picked
    world's box and label in the scene, its status line, its joint plot (one per part with
    joints, the picked world's part's shown) and, where a part has cameras, the camera chooser
    and image. `client`: the browser's viser ClientHandle.

    What a view keeps per browser lives here too, for the view to fill the panel with:
    `history`, (sim time, joint positions) of the picked world over the last seconds (the live
    view's plot), `history_world` the world it is of; `panel`, what the view last drew in the
    panel (its own key; None in a new pick); `shown`, the image's (world, camera, rendered) and
    `seen`, the seq of that world's frame last taken (only frames rendered since are shown)."""

    def __init__(self, scene: FleetScene, client: viser.ClientHandle):
        self.scene, self.client = scene, client
        n, spacing, parts = scene.n, scene.spacing, scene.parts
        gui = client.gui
        self.mark = client.scene.add_box("/picked/box", color=HIGHLIGHT_RGB, dimensions=(0.9 * spacing, 0.9 * spacing, 0.02 * spacing),
                                         wireframe=True, position=tuple(scene.grid[0]) if n else (0.0, 0.0, 0.0))  # fmt: skip
        self.label = client.scene.add_label("/picked/label", "", position=(0.0, 0.0, 0.0))
        self.picker = gui.add_number("world", 0, min=0, max=max(0, n - 1), step=1, order=ORDER["world"])
        self.world_text = gui.add_markdown("", order=ORDER["status"])
        self.plots: list[Any] = [None] * len(parts)  # per part with joints: its plot, shown while picked
        first_part = int(scene.part_of[0]) if n else 0
        for p, part in enumerate(parts):
            if part.spec.joints is not None:
                names = part.spec.joints[2]
                series = (viser.uplot.Series(label="t"), *(viser.uplot.Series(label=j, stroke=_stroke(i)) for i, j in enumerate(names)))
                self.plots[p] = gui.add_uplot(data=(np.zeros(1), *[np.zeros(1)] * len(names)), series=series,
                                              title="joint positions (rad, m) against sim time (s)", scales={"x": {"time": False}},
                                              aspect=1.5, visible=p == first_part, order=ORDER["plot"] + p / (len(parts) + 1))  # fmt: skip
        first = parts[first_part].cameras if n else ()
        self.chooser: Any = None
        self.image: Any = None
        if any(len(p.cameras) > 1 for p in parts):
            names = tuple(c[0] for c in first) or ("",)
            self.chooser = gui.add_dropdown("camera", names, initial_value=names[0], visible=len(first) > 1, order=ORDER["camera"])
        shape = next((p.cameras[0] for p in parts if p.cameras), None)
        if shape is not None:
            self.image = gui.add_image(np.full((shape[1], shape[2], 3), NO_IMAGE, np.uint8), label=first[0][0] if first else "",
                                       format="jpeg", jpeg_quality=85, visible=bool(first), order=ORDER["image"])  # fmt: skip
        self._shown_part = first_part
        self.history: collections.deque = collections.deque()
        self.history_world = -1
        self.panel: Any = None
        self.shown: tuple[int, int, bool] = (-1, -1, False)
        self.seen = np.full(1, -1, np.int64)
        self.picker.on_update(lambda _: self.mark_picked())
        self.mark_picked()

    @property
    def world(self) -> int:
        """The picked world."""
        return int(np.clip(self.picker.value, 0, self.scene.n - 1))

    def pick(self, world: int) -> None:
        """Pick `world` (as the browser's picker would)."""
        self.picker.value = world

    @property
    def cameras(self) -> tuple[tuple[str, int, int], ...]:
        """The picked world's part's cameras."""
        return self.scene.parts[self.scene.part_of[self.world]].cameras

    @property
    def camera(self) -> int:
        """The chosen camera's index in `cameras` (0 without a chooser)."""
        names = [c[0] for c in self.cameras]
        return names.index(self.chooser.value) if self.chooser is not None and self.chooser.value in names else 0

    def show_part(self) -> int:
        """The picked world's part, its plot and its cameras shown (the panel follows a pick into
        another group's worlds); call before drawing the panel."""
        p = int(self.scene.part_of[self.world])
        if p != self._shown_part:
            self._shown_part = p
            for k, plot in enumerate(self.plots):
                if plot is not None:
                    plot.visible = k == p
            names = tuple(c[0] for c in self.scene.parts[p].cameras)
            if self.chooser is not None:
                if len(names) > 1:
                    self.chooser.options = names
                self.chooser.visible = len(names) > 1
            if self.image is not None:
                self.image.visible = bool(names)
        return p

    def blank(self, camera: int) -> np.ndarray:
        """The grey image of the picked world's camera `camera`, until its frame comes."""
        _name, h, w = self.cameras[camera]
        return np.full((h, w, 3), NO_IMAGE, np.uint8)

    def mark_picked(self) -> None:
        """The picked world's box and label at its cell (the picker's callback)."""
        if not self.scene.n:
            return
        w, spacing, ns = self.world, self.scene.spacing, self.scene.namespaces[self.world]
        at = self.scene.grid[w]
        self.mark.position = tuple(at + (0.0, 0.0, 0.01 * spacing))
        self.label.position = tuple(at + (0.0, 0.0, 0.6 * spacing))
        self.label.text = f"world {w}" + (f" ({ns})" if ns and ns != f"world_{w}" else "")

    def plot_joints(self, t: np.ndarray, q: np.ndarray) -> None:
        """The picked world's joint positions q (len(t), njoint) at sim times t."""
        plot = self.plots[self.scene.part_of[self.world]]
        if plot is not None and len(t):
            plot.data = (t, *q.reshape(len(t), -1).T)


def tints(colors: Sequence[np.ndarray]) -> dict[str, tuple[str, tuple[int, int, int]]]:
    """Each status's tint (name, rgb): of its TINT_CANDIDATES not taken by another status, the one
    whose nearest robot colour (`colors`, rgb) is farthest, the first of equals."""
    base = np.array([np.asarray(c, float) for c in colors]).reshape(-1, 3)
    out: dict[str, tuple[str, tuple[int, int, int]]] = {}
    for state, candidates in TINT_CANDIDATES.items():
        free = [c for c in candidates if c[0] not in {name for name, _ in out.values()}]
        far = [np.linalg.norm(base - c[1], axis=1).min() if len(base) else 0.0 for c in free]
        out[state] = free[int(np.argmax(far))]
    return out


def framing(grid: np.ndarray, spacing: float, fov: float) -> tuple[np.ndarray, np.ndarray]:
    """The first view's camera position and the point it looks at: the grid's centre, from the front left and
    above, far enough that a sphere holding every world's cell fills at most the vertical field
    of view `fov` (radians; the horizontal one is wider on a landscape page)."""
    lo, hi = grid.min(axis=0) - spacing / 2, grid.max(axis=0) + spacing / 2
    center = (lo + hi) / 2
    center[2] = 0.0
    radius = max(float(np.linalg.norm((hi - lo)[:2]) / 2), spacing)
    direction = np.array([-0.7, -0.9, 0.6])
    return center + direction / np.linalg.norm(direction) * radius / np.sin(fov / 2) * 1.05, center


def _stroke(i: int) -> str:
    return ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f")[i % 8]
