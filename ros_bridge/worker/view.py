"""The fleet's web view: `python -m ros_bridge.worker.view STATUS_FD` (ros_bridge/view_plan.py
starts it with the bridge and hands it the plan on standard input; in a fleet of several groups of
worlds, every group's).

The page is view_scene.py's FleetScene: every world in a grid, drawn from MuJoCo's own geometry,
each world tinted by its status; the panel shows sim time, the RTF and how many worlds are in
each state and, for each browser its own pick (view_scene.py's Pick), the picked world's
status, joint positions over the last seconds and, where its worlds have cameras, its camera's
latest RGB image. Poses and status come from the snapshot the bridge workers read
(ros_bridge/protocol/snapshot.py), at most UPDATE_RATE times a second, the panel's text and
plots PANEL_RATE times (each update one message batch to the page, and one to each browser);
the images from the cameras' sensor blocks (ros_bridge/protocol/sensor_blocks.py), each
rendered for the worlds the browsers show while the view asks (`view.camera`: the distinct
(world, camera) pairs, up to MAX_VIEW_CAMERAS a group, the first browsers' first; a browser
beyond them is told in its image's label; ros_bridge/view_plan.py's ViewCamera). A fleet of
several groups is one page: each group's snapshot, read from its own bridge's shared memory,
draws its worlds with its own robots' geoms at their places in the fleet's grid, and a
picked world's panel comes from its own group.

viser rather than foxglove-sdk or rerun: it serves its own page from this process (no app to
fetch from the internet, so a browser on an isolated machine works), instanced meshes with a
colour per instance are part of its API, and its panel (numbers, text, plots) is enough for
the picked world.
"""

from __future__ import annotations

import collections
import os
import pickle
import signal
import sys
import time as wallclock

import numpy as np

from batchsim.memory import Memory
from ros_bridge.plan import FLAG_BAD, FLAG_FROZEN, FLAG_TIMED_OUT, FleetPlan
from ros_bridge.protocol.demand import ChannelDemand
from ros_bridge.protocol.sensor_blocks import MAX_VIEW_CAMERAS, WANT_RGB, CameraRequest, SensorBlock
from ros_bridge.protocol.snapshot import Snapshot, read_snapshot
from ros_bridge.worker.process import die_with_parent
from ros_bridge.worker.view_scene import FleetScene, Pick, ScenePart, qmul, rotate
from ros_bridge.world_status import status_text

__all__ = ["FleetScene", "FleetView", "Pick", "ScenePart", "main", "qmul", "rotate"]

UPDATE_RATE = 20.0  # Hz
# The panel's text and plot: each change is a React render of the panel in the page; at 20 Hz
# beside software WebGL on 2 busy cores, the page fell behind the messages and never caught up
# (its sim time a minute late, a WebDriver call waiting minutes for its thread)
PANEL_RATE = 5.0  # Hz
PLOT_SECONDS = 10.0
NICE = 10


class _Group:
    """One group's bridge as the view reads it: its plan, its snapshot, its cameras' blocks and
    request; `first`, its first world's index among the page's worlds."""

    def __init__(self, plan: FleetPlan, memory: Memory, first: int):
        self.plan, self.spec, self.memory, self.first = plan, plan.view, memory, first
        self.n = plan.nworld
        self.snap = Snapshot()
        self.last: Snapshot | None = None  # the newest snapshot read
        cameras = plan.sensors.cameras if plan.sensors is not None else ()
        self.cameras = tuple((c.camera.name, c.camera.height, c.camera.width) for c in cameras)
        self.blocks = [SensorBlock(memory, f"cam{k}", ("rgb",)) for k in range(len(cameras))]
        self.camera = CameraRequest(memory) if self.blocks else None  # the images the loop renders for us
        self.asked: list[tuple[int, int]] = []  # the (row, camera) pairs asked of it, the first browsers' first

    def part(self) -> ScenePart:
        return ScenePart(self.spec, tuple(range(self.first, self.first + self.n)), self.cameras)

    def want(self, on: bool) -> None:
        """Ask the loop for the channels the view reads (the tf poses, the joint positions)."""
        want = ChannelDemand(self.memory, "view.want")
        if on:
            want.set([self.spec.channel] + ([self.spec.joints[0]] if self.spec.joints is not None else []))
        else:
            want.clear()
        if not on and self.camera is not None:
            self.camera.clear()
            self.asked = []

    def ask(self, pairs: list[tuple[int, int]]) -> list[tuple[int, int]]:
        """Ask the loop for the images of `pairs` ((row, camera) each, the first most wanted), where
        they changed; returns the pairs asked (up to MAX_VIEW_CAMERAS: the others wait)."""
        if self.camera is not None and list(dict.fromkeys(pairs))[: self.camera.slots] != self.asked:
            self.asked = self.camera.ask(pairs)
        return self.asked


class FleetView:
    """The live page for `plans`' worlds (one bridge's, or every group's of a fleet of several,
    numbered one after the other), fed from `memories` (their snapshots)."""

    def __init__(self, plans: list[FleetPlan], memories: list[Memory]):
        self.groups: list[_Group] = []
        for plan, memory in zip(plans, memories, strict=True):
            self.groups.append(_Group(plan, memory, sum(g.n for g in self.groups)))
        self.n = sum(g.n for g in self.groups)
        self.namespaces = [ns for g in self.groups for ns in g.plan.namespaces]
        self.status = np.zeros(self.n, np.uint8)  # every world's, from its group's newest snapshot
        self.flags = np.zeros(self.n, np.uint8)
        self.rtf = collections.deque(maxlen=int(UPDATE_RATE))  # (wall, sim) of the last second
        self.scene = FleetScene([g.part() for g in self.groups], self.namespaces)
        self.url = self.scene.url
        self.updates = 0
        self.panel_every = max(1, round(UPDATE_RATE / PANEL_RATE))

    def want(self, on: bool) -> None:
        """Ask every group's loop side for what the view reads; off, for no camera image either."""
        for g in self.groups:
            g.want(on)
        if not on:
            for pick in self.scene.picks():
                pick.shown = (-1, -1, False)

    def update(self) -> None:
        """One update of the page, sent as one batch (and one per browser): the poses, the tints
        and (PANEL_RATE times a second, or at once after a browser's pick) the panel."""
        with self.scene.server.atomic():
            self._update()

    def _update(self) -> None:
        snaps = []
        for k, g in enumerate(self.groups):
            snap = read_snapshot(g.memory, len(g.plan.channels), 0, g.n, g.snap)
            if snap is None:
                continue
            g.last = snap
            snaps.append(snap)
            if g.spec.channel in snap.channels:
                self.scene.draw(snap.channels[g.spec.channel].reshape(g.n, -1, 7), k)
            self.status[g.first : g.first + g.n] = snap.status
            self.flags[g.first : g.first + g.n] = snap.flags
        if not snaps:
            return
        time = max(s.time for s in snaps)
        self.rtf.append((wallclock.monotonic(), time))
        self.scene.tint(self.status, self.flags)
        panel = self.updates % self.panel_every == 0
        if panel:
            self._fleet(time)
        self.updates += 1
        picks = self.scene.picks()
        rendered = self._ask(picks) if self.scene.cameras_shown else set()
        for pick in picks:
            with pick.client.atomic():
                pick.show_part()
                self._record(pick)
                if panel or pick.world != pick.panel:
                    self._panel(pick)
                if pick.image is not None:
                    self._image(pick, rendered)

    def _group(self, world: int) -> tuple[_Group, int]:
        """World `world`'s group and its index there."""
        g = self.groups[self.scene.part_of[world]]
        return g, world - g.first

    def _ask(self, picks: list[Pick]) -> set[tuple[int, int]]:
        """Each group's loop asked for the images its worlds' picks show (the first browsers'
        first); returns the (world, camera) pairs asked."""
        wanted: list[list[tuple[int, int]]] = [[] for _ in self.groups]
        for pick in picks:
            g, row = self._group(pick.world)
            if g.blocks:
                wanted[self.groups.index(g)].append((row, pick.camera))
        return {(g.first + row, k) for g, pairs in zip(self.groups, wanted, strict=True) for row, k in g.ask(pairs)}

    def _image(self, pick: Pick, rendered: set[tuple[int, int]]) -> None:
        """The newest frame of the pick's world's chosen camera, once the loop renders it."""
        w, k = pick.world, pick.camera
        g, row = self._group(w)
        if not g.blocks:  # a world without a camera: the image is hidden (Pick.show_part)
            pick.shown = (w, -1, False)
            return
        block, on = g.blocks[k], (w, k) in rendered
        if (w, k, on) != pick.shown:  # only frames rendered from now: an older one may be long stale
            pick.shown = (w, k, on)
            pick.seen[0] = block.seq[row]
            pick.image.image = pick.blank(k)
            name = pick.cameras[k][0]
            pick.image.label = f"{name} (world {w})" if on else (
                f"{name} (world {w}): not shown, the view renders {MAX_VIEW_CAMERAS} cameras at once (the first browsers')")
        if on:
            rows, parts, _time, data = block.read_worlds(np.array([row]), pick.seen)
            if rows.size and parts[0] & WANT_RGB:
                pick.image.image = data["rgb"][0]

    def _fleet(self, time: float) -> None:
        """The page's fleet line: sim time, RTF, how many worlds are in each state."""
        (w0, s0), (w1, s1) = self.rtf[0], self.rtf[-1]
        rtf = (s1 - s0) / (w1 - w0) if w1 > w0 else 0.0
        frozen = int(((self.flags & FLAG_FROZEN) != 0).sum())
        bad = int(((self.flags & FLAG_BAD) != 0).sum())
        timeout = int(((self.flags & FLAG_TIMED_OUT) != 0).sum())
        self.scene.fleet_text.content = (
            f"**{self.n} worlds** · sim time {time:.2f} s · RTF {rtf:.2f}  \n"
            f"running {self.n - frozen} · frozen {frozen} · bad command {bad} · command timeout {timeout}"
        )

    def _panel(self, pick: Pick) -> None:
        """A browser's panel: its picked world's status line and joint plot."""
        w = pick.panel = pick.world
        text = f"**{self.namespaces[w] or '/'}** (world {w}): {status_text(int(self.status[w]), int(self.flags[w]))}"
        if pick.world_text.content != text:
            pick.world_text.content = text
        if pick.history:
            pick.plot_joints(np.array([h[0] for h in pick.history]), np.array([h[1] for h in pick.history]))

    def _record(self, pick: Pick) -> None:
        """The pick's world's joint positions of this update into its plot's history (a new
        pick starts its own)."""
        g, row = self._group(pick.world)
        if pick.history_world != pick.world:
            pick.history.clear()
            pick.history_world = pick.world
        joints, snap = g.spec.joints, g.last
        if joints is not None and snap is not None and joints[0] in snap.channels:
            pick.history.append((snap.time, snap.channels[joints[0]][row, list(joints[1])]))
            while pick.history and pick.history[0][0] < snap.time - PLOT_SECONDS:
                pick.history.popleft()


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    status = os.fdopen(int(argv[0]), "w", buffering=1)
    die_with_parent()
    os.nice(NICE)  # the loop and the workers come first for the cores
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the physics process, which stops us
    stopping: list[int] = []
    signal.signal(signal.SIGTERM, lambda signum, frame: stopping.append(signum))
    try:  # one bridge's plan, or every group's of a fleet of several, the first group's first
        plans: list[FleetPlan] = pickle.load(sys.stdin.buffer)
    except (EOFError, pickle.UnpicklingError):
        return 0
    memories = [Memory.attach(plan.layout, plan.memory_name) for plan in plans]
    try:
        try:
            view = FleetView(plans, memories)
        except OSError as e:  # the port is taken, the address is not this host's
            where = f"{plans[0].view.host}:{plans[0].view.port}"
            status.write(f"warning: view: cannot serve on {where}: {e.strerror or e}; the simulation goes on\n")
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
    finally:
        for memory in memories:
            memory.close()
    return 0


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    os._exit(code)
