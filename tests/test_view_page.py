"""The web view's page itself (ros_bridge/worker/view_scene.py), without ROS: the first view frames
every world, the tints stand apart from the robots' colours, and the picked world is marked and
named (issue 46: at 256 worlds the first view cut off the front rows; nothing said which robot is
world 13; the orange "bad command" tint was close to the arm's own colour)."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest
from conftest import need

need("viser")

from view_clients import connect, wait  # noqa: E402

import batchsim  # noqa: E402
from ros_bridge.view_plan import ViewSpec, view_spec  # noqa: E402
from ros_bridge.worker.view_scene import TINT_CANDIDATES, FleetScene, ScenePart, framing, tints  # noqa: E402


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _inside_view(camera: np.ndarray, look_at: np.ndarray, fov: float, aspect: float, points: np.ndarray) -> bool:
    """Whether every point projects inside a pinhole camera's frame (vertical `fov`, width/height `aspect`), up z."""
    forward = (look_at - camera) / np.linalg.norm(look_at - camera)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    rel = points - camera
    depth = rel @ forward
    x, y = (rel @ right) / depth, (rel @ up) / depth
    half = np.tan(fov / 2)
    return bool((depth > 0).all() and (np.abs(y) <= half).all() and (np.abs(x) <= half * aspect).all())


@pytest.mark.parametrize("n", [1, 16, 256, 1024])
def test_the_first_view_frames_every_worlds_cell(n):
    spacing = 2.0
    cols = int(np.ceil(np.sqrt(n)))
    k = np.arange(n)
    grid = np.stack([(k % cols) * spacing, (k // cols) * spacing, np.zeros(n)], -1)
    fov = 75.0 * np.pi / 180.0
    camera, center = framing(grid, spacing, fov)
    np.testing.assert_allclose(center, [grid[:, 0].max() / 2, grid[:, 1].max() / 2, 0.0])
    corners = np.concatenate([grid + (dx, dy, dz) for dx in (-1, 1) for dy in (-1, 1) for dz in (0, spacing / 2)])
    assert _inside_view(camera, center, fov, 1.0, corners)  # a square page; a wide one sees more


def test_the_old_first_view_cut_off_the_front_rows_at_256_worlds():
    """What the page did before: the camera at `(-0.7, -0.9, 0.6) * (half the grid's width + spacing)`."""
    spacing, n = 2.0, 256
    k = np.arange(n)
    grid = np.stack([(k % 16) * spacing, (k // 16) * spacing, np.zeros(n)], -1)
    center = np.array([grid[:, 0].max() / 2, grid[:, 1].max() / 2, 0.0])
    old = center + np.array([-0.7, -0.9, 0.6]) * (max(center[0], 1.0) + spacing)
    assert not _inside_view(old, center, 75.0 * np.pi / 180.0, 1.0, grid)


def test_each_tint_stands_apart_from_every_robot_colour_and_from_the_others():
    arm_orange = np.array([255, 140, 0])  # a robot painted the old "bad command" orange
    chosen = tints([arm_orange, np.array([200, 200, 200])])
    rgbs = [np.array(rgb) for _, rgb in chosen.values()]
    assert len({name for name, _ in chosen.values()}) == len(TINT_CANDIDATES)
    assert all(np.linalg.norm(rgb - arm_orange) > 150 for rgb in rgbs), chosen
    assert chosen["bad command"][0] != "orange"


def _arm_scene(n: int, joints=None) -> FleetScene:
    sim = batchsim.make("arm", 1, "cpu")
    spec = view_spec(sim, 0, tuple(range(1, sim.model.nbody)), "127.0.0.1", _free_port())
    sim.shutdown()
    return FleetScene([ScenePart(ViewSpec(spec.geoms, 0, spec.spacing, "127.0.0.1", spec.port, joints), tuple(range(n)))],
                      [f"world_{w}" for w in range(n)])  # fmt: skip


def test_the_picked_world_is_marked_and_named_and_the_legend_names_the_tints():
    scene = _arm_scene(16)
    client = None
    try:
        client, pick = connect(scene)
        assert pick.label.text == "world 0"
        pick.pick(13)  # as the browser's picker does (its callback marks it)
        assert pick.label.text == "world 13"
        np.testing.assert_allclose(np.array(pick.mark.position)[:2], scene.grid[13, :2])
        assert scene.tint_text.content.startswith("tints: ") and "bad command" in scene.tint_text.content
    finally:
        if client is not None:
            client.close()
        scene.server.stop()


def test_each_browser_keeps_its_own_pick_by_number_or_by_click():
    """Issue 46: the pick was the page's, so a second browser's pick moved the first's box, label
    and panel. Two browsers on one page: one types a world's number, the other clicks a world;
    each keeps its own, and is told only of its own box and label (its own scope's)."""
    scene = _arm_scene(16, joints=(1, (0, 1), ("j0", "j1")))
    clients = []
    try:
        a, pick_a = connect(scene)
        b, pick_b = connect(scene)
        clients += [a, b]
        assert [p.client.client_id for p in scene.picks()] == [pick_a.client.client_id, pick_b.client.client_id]

        def told(client, w: int) -> bool:  # what the browser itself was sent: its box at w's cell, its label naming w
            box, label = client.scene_node("/picked/box"), client.scene_node("/picked/label")
            return label.get("text") == f"world {w}" and np.allclose(box.get("position", (np.nan,) * 3)[:2], scene.grid[w, :2])

        a.type_world(13)
        wait(lambda: pick_a.world == 13, 10, "a's typed pick")
        node = scene.handles[0][0].name  # a geom's instanced mesh: instance k is world k
        b.click(node, 5)
        wait(lambda: pick_b.world == 5, 10, "b's clicked pick")
        wait(lambda: told(a, 13) and told(b, 5), 10, f"each browser's box and label\n{a.scene_node('/picked/label')}\n{b.scene_node('/picked/label')}")
        for pick, w in ((pick_a, 13), (pick_b, 5)):
            assert pick.world == w and pick.label.text == f"world {w}"
            np.testing.assert_allclose(np.array(pick.mark.position)[:2], scene.grid[w, :2])
        t = np.array([0.0, 0.1])
        pick_a.plot_joints(t, np.full((2, 2), 13.0))  # each browser's plot its own (the views fill them)
        pick_b.plot_joints(t, np.full((2, 2), 5.0))
        assert pick_a.plots[0] is not pick_b.plots[0]
        assert np.all(pick_a.plots[0].data[1] == 13.0) and np.all(pick_b.plots[0].data[1] == 5.0)
        a.click(node, 7)  # a click picks in the browser that clicked only
        wait(lambda: pick_a.world == 7 and told(a, 7), 10, "a's clicked pick")
        time.sleep(0.3)  # anything else the click did has been sent
        assert pick_b.world == 5 and told(b, 5)
        assert not any(m.get("updates", {}).get("text") == "world 7" for m in b.messages)  # a's label never reached b
        b.close()  # a browser that leaves is forgotten
        wait(lambda: [p.client.client_id for p in scene.picks()] == [pick_a.client.client_id], 10, "b forgotten")
        assert scene.pick_of(pick_b.client.client_id) is None
    finally:
        for client in clients:
            client.close()
        scene.server.stop()
