"""The web view's camera images, physics side, in process: the view's request (`view.camera`)
makes exactly the asked worlds' cameras wanted (as a subscriber would), beside the workers' own
want bits, and renders them; dropping the request leaves the workers' bits as they were. Each
browser asks for its own world's camera, up to MAX_VIEW_CAMERAS distinct ones. The page itself:
tests/test_view.py, in a browser; several browsers' images: tests/test_groups_view.py."""

from __future__ import annotations

import numpy as np

import batchsim
from ros_bridge.protocol.sensor_blocks import (
    MAX_VIEW_CAMERAS,
    WANT_DEPTH,
    WANT_RGB,
    CameraRequest,
    SensorBlock,
    camera_request_arrays,
)
from ros_bridge.sensor_topics import SensorFeed, sensor_plan
from ros_bridge.view_plan import ViewCamera


def _rovers() -> tuple:
    """Three rovers with a small camera, their sensor plan, the view's request in plain arrays."""
    sim = batchsim.make("rover", 3, "cpu", sensors={"sensors": {"camera_resolution": [16, 12], "camera_rate": 50}})
    sim.configure()
    sim.activate()
    plan = sensor_plan(sim)
    memory = {name: np.zeros(shape, dtype) for name, shape, dtype in [*plan.arrays(3), *camera_request_arrays()]}
    return sim, plan, memory, ViewCamera(memory)


def test_the_views_request_wants_exactly_that_worlds_camera_and_dropping_it_clears_it():
    sim, plan, memory, camera = _rovers()
    assert (memory["view.camera"] == -1).all()  # a new segment's zeros would ask for world 0
    feed = SensorFeed(sim, memory, plan, None, camera)
    block = SensorBlock(memory, "cam0", ("rgb", "depth"))
    workers = memory["sensors.want"]
    workers[2, 0] = WANT_DEPTH  # a subscriber of world 2's depth image
    before = workers.copy()
    time = 0.0

    def run(periods: int) -> None:
        nonlocal time
        for _ in range(periods):
            feed.update(sim, time, 0.01)
            time += 0.01

    run(3)
    assert sim.sensors.wanted("front_camera").tolist() == [False, False, True]
    memory["view.camera"][0] = (1, 0)  # the page picked world 1
    run(10)
    assert sim.sensors.wanted("front_camera").tolist() == [False, True, True]
    assert not sim.sensors.wanted("base_scan").any()  # the camera only
    assert np.array_equal(workers, before)  # the workers' rows are theirs: ORed into a copy
    assert block.seq[0] == 0 and block.seq[1] > 0
    assert block.parts[1] & WANT_RGB and not block.parts[2] & WANT_RGB  # world 2 asked for depth only
    assert block.data["rgb"][1].std() > 0  # a rendered image, not the zeros it started as
    memory["view.camera"][:] = -1  # the page closed
    run(3)
    assert sim.sensors.wanted("front_camera").tolist() == [False, False, True]
    sim.shutdown()


def test_each_browsers_world_camera_renders_up_to_the_limit():
    """Two browsers showing worlds 0 and 2: both worlds' camera renders in the one batched render;
    a pair asked twice is asked once, and beyond MAX_VIEW_CAMERAS distinct pairs the rest wait."""
    sim, plan, memory, camera = _rovers()
    feed = SensorFeed(sim, memory, plan, None, camera)
    block = SensorBlock(memory, "cam0", ("rgb", "depth"))
    view = CameraRequest(memory)  # the view process's side of the same array
    assert view.slots == MAX_VIEW_CAMERAS and camera.request.asked() == set()
    assert view.ask([(0, 0), (2, 0), (0, 0)]) == [(0, 0), (2, 0)]
    assert camera.request.asked() == {(0, 0), (2, 0)}
    time = 0.0
    for _ in range(10):
        feed.update(sim, time, 0.01)
        time += 0.01
    assert sim.sensors.wanted("front_camera").tolist() == [True, False, True]
    assert block.seq[0] > 0 and block.seq[1] == 0 and block.seq[2] > 0
    assert block.data["rgb"][0].std() > 0 and block.data["rgb"][2].std() > 0
    many = [(w, 0) for w in range(MAX_VIEW_CAMERAS + 2)]
    assert view.ask(many) == many[:MAX_VIEW_CAMERAS]  # the first browsers' first; the others wait
    assert camera.request.asked() == set(many[:MAX_VIEW_CAMERAS])
    view.clear()
    assert camera.request.asked() == set()
    sim.shutdown()
