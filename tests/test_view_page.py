"""The web view's page itself (ros_bridge/worker/view_scene.py), without ROS: the first view frames
every world, the tints stand apart from the robots' colours, and the picked world is marked and
named (issue 46: at 256 worlds the first view cut off the front rows; nothing said which robot is
world 13; the orange "bad command" tint was close to the arm's own colour)."""

from __future__ import annotations

import socket

import numpy as np
import pytest
from conftest import need

need("viser")

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


def test_the_picked_world_is_marked_and_named_and_the_legend_names_the_tints():
    sim = batchsim.make("arm", 1, "cpu")
    spec = view_spec(sim, 0, tuple(range(1, sim.model.nbody)), "127.0.0.1", _free_port())
    sim.shutdown()
    scene = FleetScene([ScenePart(ViewSpec(spec.geoms, 0, spec.spacing, "127.0.0.1", spec.port), tuple(range(16)))],
                       [f"world_{w}" for w in range(16)])  # fmt: skip
    try:
        assert scene.label.text == "world 0"
        scene.picker.value = 13
        scene._mark()  # the picker's callback, as a browser's change runs it
        assert scene.label.text == "world 13"
        np.testing.assert_allclose(np.array(scene.mark.position)[:2], scene.grid[13, :2])
        assert scene.tint_text.content.startswith("tints: ") and "bad command" in scene.tint_text.content
    finally:
        scene.server.stop()
