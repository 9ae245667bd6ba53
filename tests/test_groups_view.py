"""The live web view of a fleet of two groups of worlds (ros_bridge/bridge.py's join_bridges): one
view process for both groups' bridges, and the page's data as it makes it (worker/view.py's
FleetView over every group's plan and snapshot): each world drawn with its own group's robots in
its own cell of the fleet's grid, a browser's picked world's panel (status, camera image) from
its own group, and each browser (a websocket client, tests/view_clients.py) its own pick. The
page in a browser: tests/test_view.py.

The fleet: group `arms`, 2 worlds of an arm (worlds 0 and 1), and group `yard`, 2 worlds of an
arm beside a rover (worlds 2 and 3), each group's bridge in this process (workers=0) on its own
ROS domain.
"""

from __future__ import annotations

import socket

import numpy as np
import pytest
from conftest import need
from depot import DEPOT
from ros_fleet import LOCALHOST, domain_id, release_domain

rclpy = need("rclpy")
need("viser")

from view_clients import connect, wait  # noqa: E402

import batchsim  # noqa: E402
from batchsim.cli.runner import group_options  # noqa: E402
from batchsim.loop import SimLoop  # noqa: E402

pytestmark = pytest.mark.ros


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_the_live_view_draws_every_groups_worlds_with_their_own_robots(monkeypatch):
    from ros_bridge.bridge import join_bridges, open_bridge
    from ros_bridge.options import BridgeOptions, ViewOptions
    from ros_bridge.protocol.sensor_blocks import CameraRequest
    from ros_bridge.worker.view import PANEL_RATE, UPDATE_RATE, FleetView

    domain = domain_id(62)
    for key, value in {**LOCALHOST, "ROS_DOMAIN_ID": str(domain)}.items():
        monkeypatch.setenv(key, value)
    groups = batchsim.make_groups(DEPOT, "cpu", sensors={"sensors": {"camera_resolution": [16, 12], "camera_rate": 50}})
    loops = []
    for _group, sim in groups:
        sim.configure()
        sim.activate()
        loops.append(SimLoop(sim, control_rate=100.0, rtf=0.0))
    loops[0].join(loops[1])
    options = BridgeOptions(workers=0, view=ViewOptions(port=_free_port()))
    bridges, live, browsers = [], None, []
    try:
        for (group, sim), loop in zip(groups, loops, strict=True):
            bridges.append(open_bridge(sim, loop, group_options(options, group)))
        process = join_bridges(bridges, [group.name for group, _ in groups])
        assert process is not None and process.url is not None  # one view process, for both groups
        process.close()  # one view at a time asks for a camera image: the one below, from here
        # the page's data, made as that process makes it, from the same plans and snapshots
        live = FleetView([b.plan for b in bridges], [b.host.memory for b in bridges])
        live.want(True)
        scene = live.scene

        def shown() -> None:
            for _ in range(3):
                loops[0].run_period()
            live.update()

        shown()
        assert live.namespaces == ["world_0", "world_1", "world_2", "world_3"]
        assert [part.worlds for part in scene.parts] == [(0, 1), (2, 3)]
        arms, yard = (part.spec.geoms for part in scene.parts)
        assert not any(g.name.startswith("rover/") for g in arms) and any(g.name.startswith("rover/") for g in yard)
        assert scene.fleet_text.content.startswith("**4 worlds** · sim time")
        assert "running 4 · frozen 0" in scene.fleet_text.content
        for part, handles in zip(scene.parts, scene.handles, strict=True):
            assert len(handles) == len(part.spec.geoms)  # one instanced mesh per geom, an instance per world
            moving = [k for k, g in enumerate(part.spec.geoms) if g.anchor >= 0]
            for k in moving:  # each world's robots in its own cell: the same pose there (nothing moves them)
                at = handles[k].batched_positions - scene.grid[list(part.worlds)]
                assert len(at) == 2 and np.allclose(at[0], at[1], atol=1e-3)
                assert np.linalg.norm(at[0]) < 5.0
        base = next(k for k, g in enumerate(yard) if g.name.startswith("rover/") and g.anchor >= 0)
        drawn = scene.handles[1][base].batched_positions[:, :2] - scene.grid[[2, 3], :2]
        assert np.allclose(drawn[:, 1], 2.0, atol=0.3)  # the rover where the fleet file put it (y = 2)
        a, pick = connect(scene)  # a browser on the page: its own pick, world 0 at first
        browsers.append(a)
        shown()
        assert pick.image is not None and not pick.image.visible  # world 0's group has no camera
        for world in (3, 1):  # a world of the second group, then of the first: each its own group's status
            a.type_world(world)
            wait(lambda world=world: pick.world == world, 10, f"world {world} picked")
            shown()
            assert pick.world_text.content == f"**world_{world}** (world {world}): running"
            if world == 3:  # the rover's camera, of world 3 (its group's second world), rendered for the page
                assert pick.image.visible and pick.image.label == "rover/front_camera (world 3)"
                assert bridges[1].camera.request.asked() == {(1, 0)} and bridges[0].camera is None
                for _ in range(50):
                    if pick.image.image.std() > 5:  # not the grey it shows until a frame comes
                        break
                    shown()
                assert pick.image.image.shape == (12, 16, 3) and pick.image.image.std() > 5
            else:
                assert not pick.image.visible and bridges[1].camera.request.asked() == set()
        # issue 46: a second browser keeps its own pick, status, plot and camera image: the first
        # browser on world 3, the second clicks world 2 (the yard's first world), each its own camera
        a.type_world(3)
        b, other = connect(scene)
        browsers.append(b)
        yard_mesh = scene.handles[1][base].name  # instance k: the yard's k-th world
        b.click(yard_mesh, 0)
        wait(lambda: pick.world == 3 and other.world == 2, 10, "both browsers' picks")
        for _ in range(50):
            shown()
            if pick.image.image.std() > 5 and other.image.image.std() > 5:
                break
        assert bridges[1].camera.request.asked() == {(1, 0), (0, 0)}  # both worlds' camera, one render
        for p, world in ((pick, 3), (other, 2)):
            assert p.world_text.content == f"**world_{world}** (world {world}): running"
            assert p.image.label == f"rover/front_camera (world {world})" and p.image.image.std() > 5
            assert p.history_world == world  # its plot's history (this fleet's groups plot no joints)
        # beyond the cameras the view renders at once (MAX_VIEW_CAMERAS; here 1), the later browser's label says so
        yard = live.groups[1]
        yard.camera, full = CameraRequest({"view.camera": bridges[1].host.memory["view.camera"][:1]}), yard.camera
        full.clear()  # the request's first row only, from here
        shown()
        assert bridges[1].camera.request.asked() == {(1, 0)} and pick.image.label == "rover/front_camera (world 3)"
        assert other.image.label.startswith("rover/front_camera (world 2): not shown, the view renders")
        yard.camera = full
        shown()
        assert bridges[1].camera.request.asked() == {(1, 0), (0, 0)} and other.image.label == "rover/front_camera (world 2)"
        b.type_world(0)  # the second browser to the arms' world 0: no camera, the arms' plot; the first's unmoved
        wait(lambda: other.world == 0, 10, "world 0 picked")
        shown()
        assert bridges[1].camera.request.asked() == {(1, 0)}
        assert not other.image.visible and other.history_world == 0
        assert other.world_text.content == "**world_0** (world 0): running"
        assert pick.world == 3 and pick.world_text.content == "**world_3** (world 3): running" and pick.image.visible
        assert pick.history_world == 3 and pick.image.label == "rover/front_camera (world 3)"
        b.type_world(2)
        wait(lambda: other.world == 2, 10, "world 2 picked")
        shown()
        assert bridges[1].camera.request.asked() == {(1, 0), (0, 0)}
        b.close()  # a browser that leaves is forgotten, and its camera no longer rendered
        wait(lambda: len(scene.picks()) == 1, 10, "the second browser forgotten")
        shown()
        assert bridges[1].camera.request.asked() == {(1, 0)}
        # the poses every update, the panel's text PANEL_RATE times a second (at 20 Hz a page on
        # software WebGL fell behind its messages for good): counted where the page would get them
        sent: list[str] = []

        class Counted:
            def __init__(self, content: str):
                self._content = content

            @property
            def content(self) -> str:
                return self._content

            @content.setter
            def content(self, value: str) -> None:
                sent.append(value)
                self._content = value

        scene.fleet_text = Counted(scene.fleet_text.content)
        for _ in range(20):
            shown()
        assert len(sent) == 20 * PANEL_RATE / UPDATE_RATE, sent
    finally:
        for browser in browsers:
            browser.close()
        if live is not None:
            live.want(False)
            live.scene.server.stop()
        for b in bridges:
            b.host.close()
        for _group, sim in groups:
            sim.shutdown()
        release_domain(domain)


def test_a_killed_view_process_is_said_once_and_the_fleet_goes_on(tmp_path):
    """Before, a view process that died left the page frozen and said nothing (issue 47's review)."""
    import os
    import signal
    import time

    from ros_fleet import alive, batchsim_process, children, cmdline

    domain = domain_id(62)
    log = tmp_path / "log"
    proc = batchsim_process(["--worlds", "2", "--controllers", "none", "--view", "--view-port", str(_free_port())], domain, log)
    try:
        deadline = time.monotonic() + 90
        while "batchsim: view: http" not in (log.read_text() if log.exists() else ""):
            assert proc.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.2)
        view = next(c for c in children(proc.pid) if "ros_bridge.worker.view" in cmdline(c))
        os.kill(view, signal.SIGKILL)
        said = "batchsim: warning: view: its process was killed by signal 9; the page no longer updates, the simulation goes on"
        while said not in log.read_text():
            assert time.monotonic() < deadline, log.read_text()
            time.sleep(0.2)
        time.sleep(2.0)
        assert alive(proc.pid) and log.read_text().count(said) == 1
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0, log.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
        release_domain(domain)
