"""Cameras, lidars and sensor noise (batchsim.sensors), on every shipped backend.

The scene (tests/scenes/sensor_box.xml) is a sensor head facing a wall whose face is at
x = 1.9 m, with a blue marker on it at a known place. World 0's head stays at x = 0, world
1's is driven to x = 0.4, so the two see the wall at 1.9 m and 1.5 m.

Tolerances: depth and ranges within 1 mm (float32 ray casting is exact to ~1e-6 m here;
the OpenGL depth buffer, 24 bits with reversed Z, to ~1e-5 m at 2 m); the marker's
centroid within half a pixel of where the intrinsics project it (pixel quantization).
"""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from arrays import host

import batchsim
from batchsim import ModelError, SensorConfigError
from batchsim.loop.sampler import SensorSampler
from batchsim.sensors import LidarKind, SensorConfig
from batchsim.sensors.camera import project

SCENE = Path(__file__).parent / "scenes" / "sensor_box.xml"
WALL = 1.9  # m, the wall's face
SHIFT = 0.4  # m, world 1's head
DEPTH_TOL = 1e-3  # m
MARKER = np.array([0.6, 0.3, WALL - 0.02])  # the marker's face centre, in the camera's optical frame


@pytest.fixture(scope="module")
def box(shipped_backend):
    """Two worlds of the scene on each shipped backend; world 1's head moved to x = SHIFT."""
    sim = batchsim.make(str(SCENE), 2, shipped_backend)
    sim.configure()
    sim.activate()
    sim.command[1, 0] = SHIFT
    for _ in range(10):  # 0.2 s: the head's servo is critically damped at 100 rad/s
        sim.write()
        sim.step(10)
    sim.read()
    assert abs(sim.state[0, 0]) < 1e-6 and abs(sim.state[1, 0] - SHIFT) < 1e-5
    yield sim
    sim.shutdown()


def _angles(ld) -> np.ndarray:
    return np.arctan2(ld.directions[:, 1], ld.directions[:, 0])


# ---------------------------------------------------------------- known geometry, every backend


def test_depth_equals_the_known_distance(box):
    rgb, depth = box.render("front")
    assert rgb.shape == (2, 24, 32, 3) and rgb.dtype == np.uint8
    assert depth.shape == (2, 24, 32) and depth.dtype == np.float32
    # planar depth: every pixel on the wall face reads its distance along the optical axis
    wall = depth[:, 11:15, 4:12]  # left of centre, clear of the marker and the floor
    np.testing.assert_allclose(wall[0], WALL, atol=DEPTH_TOL)
    np.testing.assert_allclose(wall[1], WALL - SHIFT, atol=DEPTH_TOL)


@pytest.mark.parametrize("name", ["scan", "fan", "cloud"])
def test_lidar_ranges_equal_the_known_distance(box, name):
    ld = box.sensors.lidar(name)
    ranges = box.scan(name)
    assert ranges.shape == (2, ld.nray) and ranges.dtype == np.float32
    # every ray meets the wall's plane: range = distance / (cos(azimuth) cos(elevation))
    along_x = ld.directions[:, 0]
    for world, distance in ((0, WALL), (1, WALL - SHIFT)):
        np.testing.assert_allclose(ranges[world], distance / along_x, atol=DEPTH_TOL)
    points = ld.points(ranges)
    np.testing.assert_allclose(points[0, :, 0], WALL, atol=DEPTH_TOL)


def test_every_lidar_declaration_is_found(box):
    lidars = box.sensors.lidars
    assert lidars["fan"].kind is LidarKind.RANGEFINDER  # mujoco_ros2_control's replicated rangefinders
    assert lidars["scan"].kind is LidarKind.RAYCAST  # the <lidar> element
    assert lidars["cloud"].kind is LidarKind.RAYCAST and lidars["cloud"].is_3d  # mujoco.plugin.lidar
    # the rangefinders' fan, measured from the geometry, is the <lidar> element's
    for name in ("fan", "scan"):
        ld = lidars[name]
        assert (ld.nray, ld.site) == (5, "lidar")
        np.testing.assert_allclose([ld.angle_min, ld.angle_max, ld.angle_increment], [-0.5, 0.5, 0.25], atol=1e-6)
        np.testing.assert_allclose(_angles(ld), np.linspace(-0.5, 0.5, 5), atol=1e-6)
    assert (lidars["cloud"].nrow, lidars["cloud"].ncol, lidars["cloud"].rate) == (2, 3, 5.0)


@pytest.mark.parametrize("camera", ["front", "pinhole"])
def test_intrinsics_project_where_the_camera_sees(box, camera):
    """The marker's centroid in the image is where CameraInfo's K projects it."""
    info = box.sensors.camera(camera).info
    rgb = box.render(camera, worlds=[0]).rgb[0]
    # blueness, so that pixels the marker covers in part weigh in part
    weight = np.clip(rgb[..., 2].astype(float) - rgb[..., 0], 0, None)
    assert 4 <= (weight > 100).sum() <= 40
    v, u = np.indices(weight.shape)
    centroid = [(u * weight).sum() / weight.sum(), (v * weight).sum() / weight.sum()]
    np.testing.assert_allclose(centroid, project(info, MARKER), atol=0.5)


def test_two_worlds_see_different_images(box):
    rgb, depth = box.render("front")
    assert not np.array_equal(rgb[0], rgb[1])
    assert abs(float(depth[0, 12, 8]) - float(depth[1, 12, 8]) - SHIFT) < DEPTH_TOL
    # a subset renders those worlds only, in order
    one = box.render("front", worlds=[1])
    np.testing.assert_array_equal(one.rgb[0], rgb[1])
    np.testing.assert_allclose(box.scan("scan", worlds=np.array([False, True]))[0], box.scan("scan")[1])


def test_rows_and_noise_follow_the_order_the_worlds_are_listed_in(shipped_backend):
    """render, render_async and scan give row i to worlds[i], and world w's noise is world w's,
    whatever the order: cpu and mjx once refused an unsorted subset ("ids must be sorted"), and
    a sharded fleet gave the rows in shard order while drawing the noise in the caller's."""
    config = {"sensors": {**NOISE["sensors"], "seed": 7}}
    listed, whole = (batchsim.make(str(SCENE), 3, shipped_backend, sensors=config) for _ in range(2))
    for sim in (listed, whole):  # world 2's head moved: each world sees the wall at its own distance
        sim.configure()
        sim.activate()
        sim.command[2, 0] = SHIFT
        for _ in range(10):
            sim.write()
            sim.step(10)
    order = [2, 0]  # on two devices, world 2 is on the second and world 0 on the first
    # the same noise draws on both systems: each call takes one draw per world it names
    scan, expect = listed.scan("scan", worlds=order), whole.scan("scan")[order]
    assert np.nanmean(scan[0]) < np.nanmean(scan[1]) - SHIFT / 2  # world 2 first
    np.testing.assert_allclose(scan, expect, atol=DEPTH_TOL)
    for frames, all_frames in (
        (listed.render("front", worlds=order), whole.render("front")),
        (listed.render_async("front", worlds=order).result(), whole.render_async("front").result()),
    ):
        assert frames.depth.shape == (2, 24, 32)
        np.testing.assert_allclose(frames.depth, all_frames.depth[order], atol=DEPTH_TOL)
        assert np.mean(np.abs(frames.rgb.astype(int) - all_frames.rgb[order].astype(int)) > 1) < 0.02
    assert list(listed.render_async("front", worlds=order).worlds) == order
    listed.shutdown()
    whole.shutdown()


def test_the_cpu_ray_caster_takes_the_worlds_in_any_order():
    """HostSensors.cast on a permutation of every world ([1, 0] of two) cast world 0's rays for
    row 0 (it passed ids=None whenever the count matched); each row is now the world named."""
    from mujoco import batch as mjbatch

    from batchsim.backends.host_sensors import HostSensors

    sim = batchsim.make(str(SCENE), 2, "cpu")
    sim.configure()
    sim.activate()
    sim.command[1, 0] = SHIFT
    for _ in range(10):
        sim.write()
        sim.step(10)
    m = sim.model
    batch = mjbatch.Batch(m, 2, nthread=1)
    batch.bind("qpos")[:] = sim.qstate()[0]
    batch.forward()
    host = HostSensors(m, batch)
    lidar = sim.sensors.lidar("scan")
    straight, swapped = host.cast(lidar, np.array([0, 1])), host.cast(lidar, np.array([1, 0]))
    assert np.nanmean(straight[1]) < np.nanmean(straight[0]) - SHIFT / 2
    np.testing.assert_array_equal(swapped, straight[[1, 0]])
    sim.shutdown()


def test_device_frames(box):
    frames = box.render("front", device=True)
    rgb, depth = host(frames.rgb), host(frames.depth)
    assert rgb.shape == (2, 24, 32, 3) and depth.shape == (2, 24, 32)
    # the same frames as the host path; NVIDIA's EGL (mjx renders through it on a GPU) does not
    # rasterize a scene bit-for-bit alike from call to call (seen on an H200: +-1 levels on half
    # the pixels, a few edge pixels more), so allow that and no more
    differ = np.abs(rgb.astype(int) - box.render("front").rgb.astype(int))
    assert np.mean(differ > 1) < 0.02, f"{np.mean(differ > 1):.1%} of the channels differ by more than 1 level"
    with pytest.raises(ValueError, match="every world"):
        box.render("front", worlds=[0], device=True)


@pytest.mark.parametrize("name", ["scan", "fan", "cloud"])
def test_device_scan_is_the_host_scan(box, name):
    ranges = box.scan(name, device=True)
    # the backend's own array (Warp, JAX); NumPy where it runs on the host (it has no devices)
    assert not isinstance(ranges, np.ndarray) or not hasattr(box, "available_devices")
    np.testing.assert_array_equal(host(ranges), box.scan(name))
    with pytest.raises(ValueError, match="every world"):
        box.scan(name, worlds=[0], device=True)


def test_ranges_beyond_the_limits_read_as_rep_117_on_every_backend(one_device_backend):
    """Rays closer than range_min read -inf, beyond range_max or into nothing +inf: warp converts
    on the device, the others on the host; all agree with Lidar.ranges."""
    config = {
        "sensors": {
            "lidars": {
                "near": {  # straight ahead 1.9 m (< range_min), at +-0.5 rad 2.165 m (> range_max), up: nothing
                    "site": "lidar",
                    "horizontal": {"samples": 5, "min_angle": -0.5, "max_angle": 0.5},
                    "vertical": {"samples": 2, "min_angle": 0.0, "max_angle": 1.5},
                    "range_min": 1.95,
                    "range_max": 2.1,
                }
            }
        }
    }
    sim = batchsim.make(str(SCENE), 1, one_device_backend, sensors=config)
    sim.configure()
    ranges = sim.scan("near")[0]
    ahead = WALL / np.cos(np.linspace(-0.5, 0.5, 5))
    expected = np.where(ahead < 1.95, -np.inf, np.where(ahead > 2.1, np.inf, ahead)).astype(np.float32)
    np.testing.assert_allclose(ranges[:5], expected, atol=DEPTH_TOL)
    assert np.all(ranges[5:] == np.inf)  # 1.5 rad up: over the wall
    np.testing.assert_array_equal(host(sim.scan("near", device=True))[0], ranges)
    sim.shutdown()


FALLING_BOX = """<mujoco>
  <option timestep="0.005"/>
  <worldbody>
    <light pos="0 0 3" dir="0 0 -1"/>
    <geom type="plane" size="3 3 0.1" rgba="0.4 0.4 0.4 1"/>
    <camera name="eye" pos="0 -2 0.4" xyaxes="1 0 0 0 0 1" fovy="60" resolution="16 12"/>
    <site name="lidar" pos="0 -2 0.15"/>
    <body pos="0 0 0.6"><freejoint/><geom type="box" size="0.15 0.15 0.15" rgba="0.9 0.2 0.2 1"/></body>
  </worldbody>
</mujoco>"""


@pytest.mark.skipif(importlib.util.find_spec("mujoco_warp") is None, reason="needs mujoco_warp")
def test_warp_sensor_graphs_follow_resets_and_grown_buffers(tmp_path):
    """warp captures each camera's and lidar's launches in a graph and replays it: it must show
    what launching them one by one shows, after a reset, and after the buffers grew (new arrays)."""
    path = tmp_path / "falling_box.xml"
    path.write_text(FALLING_BOX)
    lidar = {"ring": {"site": "lidar", "horizontal": {"samples": 9, "min_angle": 1.2, "max_angle": 1.9}}}
    sims = {}
    for graph in (True, False):
        # one contact per world to start with: the box's landing (4 contacts) grows the buffers;
        # devices= names one device whatever the backend fixture's two-device variant patches in
        config = {"sensors": {"lidars": lidar}}
        sim = batchsim.make(str(path), 2, "warp", devices=["cpu"], graph=graph, nconmax=1, sensors=config)
        sim.configure()
        sim.activate()
        sims[graph] = sim

    def sense() -> dict[bool, tuple[np.ndarray, np.ndarray]]:
        out = {}
        for graph, sim in sims.items():
            for _ in range(2):  # the first call captures the graph, the second replays it
                depth = host(sim.render("eye", device=True).depth).copy()
                ranges = host(sim.scan("ring", device=True)).copy()
            np.testing.assert_array_equal(sim.scan("ring"), ranges)
            out[graph] = depth, ranges
        for a, b in zip(out[True], out[False], strict=True):
            np.testing.assert_array_equal(a, b)
        return out[True]

    falling = sense()
    for sim in sims.values():
        for _ in range(40):  # 2 s: the box lands, which overflows nconmax 1
            sim.step(10)
    assert all(sim.nconmax > 1 for sim in sims.values())
    landed = sense()
    # the rays passed under the box in the air and meet it on the floor; the camera sees it lower
    assert np.isinf(falling[1]).all()
    assert np.isfinite(landed[1]).any(axis=1).all() and not np.array_equal(landed[0], falling[0])
    for sim in sims.values():
        sim.reset([1])
    again = sense()
    for a, b, c in zip(again, landed, falling, strict=True):
        np.testing.assert_array_equal(a[0], b[0])  # world 0 still on the floor
        np.testing.assert_array_equal(a[1], c[1])  # world 1 back in the air
    for sim in sims.values():
        sim.shutdown()


def test_render_async_gives_what_render_gives(box):
    job = box.render_async("front", worlds=[1])
    now = box.render("front", worlds=[1])
    rgb, depth = job.result()
    assert list(job.worlds) == [1] and rgb.shape == (1, 24, 32, 3) and depth.shape == (1, 24, 32)
    assert job.done() and job.result().rgb is rgb  # one result, kept
    # NVIDIA's EGL does not repeat a rasterization bit for bit (test_device_frames): as there
    differ = np.abs(rgb.astype(int) - now.rgb.astype(int))
    assert np.mean(differ > 1) < 0.02
    np.testing.assert_allclose(depth, now.depth, atol=DEPTH_TOL)


def test_render_async_draws_the_worlds_as_they_were_at_the_call():
    """cpu and mjx draw on a render thread while the caller steps on: from poses copied at the call."""
    sim = batchsim.make(str(SCENE), 2, "cpu")
    sim.configure()
    sim.activate()
    before = sim.render("front")
    jobs = [sim.render_async("front"), sim.render_async("front", worlds=[1])]
    sim.command[1, 0] = SHIFT  # world 1 drives towards the wall while the renders are in flight
    for _ in range(10):
        sim.write()
        sim.step(10)
    after = sim.render("front")
    assert abs(float(after.depth[1, 12, 8]) - (WALL - SHIFT)) < DEPTH_TOL  # it moved
    np.testing.assert_array_equal(jobs[0].result().rgb, before.rgb)
    np.testing.assert_array_equal(jobs[0].result().depth, before.depth)
    np.testing.assert_array_equal(jobs[1].result().depth, before.depth[1:])
    sim.shutdown()  # with no render in flight, and again with one: the render thread is joined either way
    sim = batchsim.make(str(SCENE), 2, "cpu")
    sim.configure()
    job = sim.render_async("front")
    sim.shutdown()
    assert job.result().rgb.shape == (2, 24, 32, 3)


def test_render_async_draws_depth_noise_as_render_does():
    a, b = _noisy(2), _noisy(2)
    np.testing.assert_array_equal(a.render_async("front").result().depth, b.render("front").depth)
    a.shutdown()
    b.shutdown()


def test_sampler_stamps_a_frame_with_the_time_its_state_was_taken():
    sim = batchsim.make(str(SCENE), 2, "cpu", sensors={"sensors": {"camera_rate": 100}})
    sim.configure()
    sim.activate()
    sim.sensors.want("front", [1])
    seen = []
    sampler = SensorSampler(sim, [lambda sample: seen.append(sample)])
    sim.command[1, 0] = SHIFT
    depth_at = {}
    for k in range(6):
        sim.read()
        depth_at[k * 0.01] = sim.render("front", worlds=[1]).depth
        sampler.update(sim, k * 0.01, 0.01)
        sim.write()
        sim.step(5)
    sampler.flush()
    assert [round(s.time, 6) for s in seen] == [round(k * 0.01, 6) for k in range(6)]
    for sample in seen:
        np.testing.assert_array_equal(sample.depth, depth_at[sample.time])
    assert sampler.produced["front"] == 6
    sim.shutdown()


def test_sampler_hands_out_one_frame_of_a_world_per_update():
    """Renders that finished together go out one per world and update: the bridge's shared
    memory keeps one sample per world, and a second in the same period would overwrite the
    first before a worker published it (a stamp missing from the topic)."""
    sim = batchsim.make(str(SCENE), 2, "cpu", sensors={"sensors": {"camera_rate": 100}})
    sim.configure()
    sim.activate()
    sim.sensors.want("front", [0])
    per_update: list[int] = []
    sampler = SensorSampler(sim, [lambda sample: per_update.__setitem__(-1, per_update[-1] + 1)])
    for k in range(8):  # faster than the render thread: renders pile up
        per_update.append(0)
        sampler.update(sim, k * 0.01, 0.01)
    time.sleep(0.5)  # all of them done
    for k in range(8, 16):
        per_update.append(0)
        sampler.update(sim, k * 0.01, 0.01)
    assert max(per_update) == 1, per_update
    sampler.flush()
    assert sampler.produced["front"] == 16
    sim.shutdown()


def test_a_runs_last_frames_still_rendering_when_it_stops_are_handed_out():
    """A frame asked for in a run's last period is still rendering when the loop stops: run()
    hands it out before it returns (a --duration recording's last frames were lost)."""
    from batchsim.loop import SimLoop

    sim = batchsim.make(str(SCENE), 2, "cpu", sensors={"sensors": {"camera_rate": 100}})
    sim.configure()
    sim.activate()
    sim.sensors.want("front", [0, 1])
    times: list[float] = []
    sampler = SensorSampler(sim, [lambda sample: times.append(round(sample.time, 6))])
    loop = SimLoop(sim, control_rate=100.0, rtf=0.0, duration=0.1, participants=[sampler])
    loop.run()
    assert sorted(set(times)) == [round(k * 0.01, 6) for k in range(10)]  # 0.09: the last period's
    assert sampler.produced["front"] == 20
    sim.shutdown()


# ---------------------------------------------------------------- intrinsics as data


def test_camera_info_matches_the_mjcf():
    spec = batchsim.load(str(SCENE))
    m = spec.mjmodel
    suite = batchsim.sensors.SensorSuite.build(spec, 1)
    front = suite.camera("front")
    assert (front.width, front.height) == tuple(m.cam_resolution[front.id]) == (32, 24)
    f = 24 / 2 / np.tan(np.radians(60) / 2)  # fovy 60 degrees over 24 rows
    np.testing.assert_allclose(front.info.k, [f, 0, 15.5, 0, f, 11.5, 0, 0, 1])
    np.testing.assert_allclose(front.info.p, [f, 0, 15.5, 0, 0, f, 11.5, 0, 0, 0, 1, 0])
    assert front.info.d == (0.0,) * 5 and front.info.distortion_model == "plumb_bob"
    # sensorsize 6.4 x 4.8 mm, focal 4 x 4.5 mm, principal (0.4, -0.2) mm, on 32 x 24 pixels
    pin = suite.camera("pinhole").info
    np.testing.assert_allclose([pin.fx, pin.fy, pin.cx, pin.cy], [20.0, 22.5, 13.5, 12.5], atol=1e-5)
    assert (front.image_topic, front.depth_topic, front.info_topic) == (
        "front/image_raw",
        "front/depth/image_raw",
        "front/camera_info",
    )


# ---------------------------------------------------------------- noise


NOISE = {
    "sensors": {
        "seed": 7,
        "noise": {
            "slide/position": {"stddev": 0.01, "bias_mean": 0.5},  # a joint encoder
            "slide_pos": {"stddev": 0.02, "bias_stddev": 0.1},  # an MJCF sensor, per-world bias
            "front": {"stddev": 0.05, "dropout": 0.1},  # depth
            "scan": {"mean": 0.01, "stddev": 0.03, "dropout": 0.2},  # lidar ranges
        },
    }
}


def _noisy(nworld: int, seed: int = 7):
    config = {"sensors": {**NOISE["sensors"], "seed": seed}}
    sim = batchsim.make(str(SCENE), nworld, "cpu", sensors=config)
    sim.configure()
    sim.activate()
    return sim


def _readings(sim, n: int) -> np.ndarray:
    out = []
    for _ in range(n):
        sim.read()
        out.append(sim.state.copy())
    return np.array(out)  # (n, nworld, nstate)


def test_noise_has_the_configured_mean_and_deviation():
    sim = _noisy(4)
    x = _readings(sim, 4000)
    truth = sim.true_state
    assert np.all(truth[:, 0] == 0.0) and np.all(sim.true_sensordata["slide_pos"] == 0.0)
    encoder = x[:, :, 0]
    assert abs(encoder.mean() - 0.5) < 0.002 and abs(encoder.std() - 0.01) < 0.001
    # the MJCF sensor: deviation 0.02 about a bias drawn once per world, and its state interface agrees
    sensor = x[:, :, 3]
    np.testing.assert_allclose(sensor.std(axis=0), 0.02, rtol=0.1)
    bias = sensor.mean(axis=0)
    assert np.ptp(bias) > 0.01 and np.all(np.abs(bias) < 0.5)
    np.testing.assert_array_equal(sim.sensordata["slide_pos"][:, 0], sim.state[:, 3])
    assert np.all(x[:, :, 1] == 0.0)  # velocity: not configured, not noisy
    # depth: noise on the wall pixels, and about 10% dropped to NaN
    depth = sim.render("front").depth
    assert abs(np.isnan(depth).mean() - 0.1) < 0.02
    wall = depth[:, 11:15, 4:12]
    assert abs(np.nanmean(wall) - WALL) < 0.01 and abs(np.nanstd(wall) - 0.05) < 0.01
    # ranges: mean 0.01, deviation 0.03, 20% dropped
    scans = np.array([sim.scan("scan") for _ in range(500)])
    truth = WALL / np.cos(np.linspace(-0.5, 0.5, 5))
    assert abs(np.isnan(scans).mean() - 0.2) < 0.02
    err = scans - truth
    assert abs(np.nanmean(err) - 0.01) < 0.003 and abs(np.nanstd(err) - 0.03) < 0.003
    sim.shutdown()


def test_noise_repeats_with_the_same_seed_and_is_per_world():
    a, b, c, wide = _noisy(2), _noisy(2), _noisy(2, seed=8), _noisy(4)
    ra, rb, rc, rw = (_readings(s, 20) for s in (a, b, c, wide))
    np.testing.assert_array_equal(ra, rb)
    assert not np.allclose(ra, rc)
    # world i's noise depends on (seed, i) only, not on how many worlds run beside it
    np.testing.assert_array_equal(ra, rw[:, :2])
    np.testing.assert_array_equal(a.render("front").depth, b.render("front").depth)
    np.testing.assert_array_equal(a.scan("scan", worlds=[1]), wide.scan("scan", worlds=[1]))
    for s in (a, b, c, wide):
        s.shutdown()


def test_noise_is_off_by_default():
    sim = batchsim.make(str(SCENE), 2, "cpu")
    sim.configure()
    sim.read()
    assert sim.sensors.reading_noise is None
    assert sim.true_state is sim.state and sim.true_sensordata is sim.sensordata
    np.testing.assert_array_equal(sim.scan("scan"), sim.scan("scan"))
    sim.shutdown()


# ---------------------------------------------------------------- who wants what


@pytest.mark.parametrize("backend", ["cpu", "warp"])  # worlds spread over periods; all in one launch
def test_a_camera_nobody_wants_costs_nothing(monkeypatch, backend):
    sim = batchsim.make(str(SCENE), 3, backend, sensors={"sensors": {"camera_rate": 50, "lidar_rate": 50}})
    sim.configure()
    sim.activate()
    calls = []
    render_async, render, scan = sim.render_async, sim.render, sim.scan
    monkeypatch.setattr(sim, "render_async", lambda name, worlds=None: calls.append(name) or render_async(name, worlds))
    monkeypatch.setattr(sim, "render", lambda name, worlds=None, **kw: calls.append(name) or render(name, worlds, **kw))
    monkeypatch.setattr(sim, "scan", lambda name, worlds=None, **kw: calls.append(name) or scan(name, worlds, **kw))
    sampler = SensorSampler(sim)
    period = 0.01
    for k in range(10):
        sampler.update(sim, k * period, period)
    assert calls == [] and not any(sampler.produced.values())
    sim.sensors.want("front", [2])
    sim.sensors.want("scan", [0, 1])
    for k in range(10, 20):
        sampler.update(sim, k * period, period)
    # 50 Hz at a 100 Hz loop: each world every other period, only the worlds that want it; on
    # cpu spread over the periods (world 0's scans in even periods, world 1's in odd ones), on
    # warp both worlds in one launch
    spread = not sim.sensors_batched
    sampler.flush()  # the renders still in flight
    assert calls.count("front") == 5 and calls.count("pinhole") == 0
    assert calls.count("scan") == (10 if spread else 5)
    assert sampler.produced["front"] == 5 and sampler.produced["scan"] == 10
    assert list(sampler.latest["front"].worlds) == [2] and sampler.latest["front"].rgb.shape == (1, 24, 32, 3)
    assert sampler.latest["scan"].ranges.shape == ((1, 5) if spread else (2, 5))
    sim.sensors.unwant("front")
    calls.clear()
    for k in range(20, 30):
        sampler.update(sim, k * period, period)
    assert "front" not in calls
    sim.shutdown()


def test_batched_sensors_due_together_take_turns_and_keep_their_rates():
    """On warp a camera or lidar is one launch for every world, so a period that ran both ran
    two (the sensor loop's worst period at 1024 worlds, 10.6-14.5 ms against 10 on a GPU): a
    second sensor due in the same period waits for the next one, within its own period, and
    keeps its rate and its honest stamps. Two sensors due every period still share it."""
    sim = batchsim.make(str(SCENE), 2, "warp", sensors={"sensors": {"camera_rate": 50, "lidar_rate": 25}})
    sim.configure()
    sim.activate()
    sim.sensors.want("front")
    sim.sensors.want("scan")
    stamps: dict[str, list[float]] = {"front": [], "scan": []}
    per_update: list[set[str]] = []
    sampler = SensorSampler(sim, [lambda s: (stamps[s.name].append(round(s.time, 6)), per_update[-1].add(s.name))])
    period = 0.01
    for k in range(40):
        per_update.append(set())
        sampler.update(sim, k * period, period)
    assert max(len(names) for names in per_update) == 1, per_update
    assert stamps["front"] == [round(0.02 * k, 6) for k in range(20)]  # 50 Hz, first in line
    scans = np.array(stamps["scan"])
    assert len(scans) == 10 and np.allclose(np.diff(scans), 0.04)  # 25 Hz, a period after the camera
    assert scans[0] == 0.01
    sampler.flush()

    # a 100 Hz lidar beside the 50 Hz camera: due every period, it can wait for none
    sim.shutdown()
    sim = batchsim.make(str(SCENE), 2, "warp", sensors={"sensors": {"camera_rate": 50, "lidar_rate": 100}})
    sim.configure()
    sim.activate()
    sim.sensors.want("front")
    sim.sensors.want("scan")
    sampler = SensorSampler(sim)
    for k in range(20):
        sampler.update(sim, k * period, period)
    assert sampler.produced == {**sampler.produced, "front": 10 * 2, "scan": 20 * 2}
    sim.shutdown()


# ---------------------------------------------------------------- configuration


PLUGIN_YAML = """
/**:
  ros__parameters:
    mujoco_plugins:
      heart_beat_plugin:
        type: "mujoco_ros2_control_plugins/HeartbeatPublisherPlugin"
        update_rate: 1.0
      mujoco_camera_plugin:
        type: "mujoco_ros2_control_plugins/CameraPlugin"
        camera_publish_rate: 6.0
        front:
          frame_name: camera_color_optical_frame
          info_topic: /camera/color/camera_info
          image_topic: /camera/color/image_raw
          depth_topic: /camera/aligned_depth_to_color/image_raw
        pinhole:
          camera_type: disabled
      mujoco_rangefinder_plugin:
        type: "mujoco_ros2_control_plugins/RangefinderLidarPlugin"
        publish_rate: 12.0
        fan:
          frame_name: "lidar_sensor_frame"
          min_angle: "-0.5"
          max_angle: "0.5"
          angle_increment: "0.25"
          topic: "/scan"
          range_min: "0.05"
          range_max: "2.0"
      mujoco_3d_lidar_plugin:
        type: "mujoco_ros2_control_plugins/Mujoco3dLidarPlugin"
        cloud:
          frame_name: "lidar_3d_frame"
          topic: "/points"
"""


def test_mujoco_ros2_control_plugin_yaml_reads_unchanged(tmp_path):
    path = tmp_path / "plugins.yaml"
    path.write_text(PLUGIN_YAML)
    sim = batchsim.make(str(SCENE), 1, "cpu", sensors=path)
    suite = sim.sensors
    assert suite.camera_rate == 6.0 and suite.lidar_rate == 12.0
    front = suite.camera("front")
    assert (front.frame_id, front.image_topic, front.depth_topic, front.info_topic) == (
        "camera_color_optical_frame",
        "/camera/color/image_raw",
        "/camera/aligned_depth_to_color/image_raw",
        "/camera/color/camera_info",
    )
    assert "pinhole" not in suite.cameras  # camera_type: disabled
    fan = suite.lidar("fan")
    assert (fan.frame_id, fan.topic, fan.range_min, fan.range_max) == ("lidar_sensor_frame", "/scan", 0.05, 2.0)
    assert (suite.lidar("cloud").frame_id, suite.lidar("cloud").topic) == ("lidar_3d_frame", "/points")
    assert any("HeartbeatPublisherPlugin" in w for w in suite.config.warnings)
    sim.configure()
    ranges = sim.scan("fan")[0]  # the outer rays (2.17 m) lie beyond range_max: +inf (REP 117)
    assert np.isposinf(ranges[[0, 4]]).all() and np.isfinite(ranges[1:4]).all()
    sim.shutdown()


def test_plugin_yaml_is_read_as_rcl_reads_a_parameter_file(tmp_path):
    """One YAML loader (batchsim.model.params, issue 22): a node key given twice is merged, not
    replaced by the second, and a dotted parameter name is the nested one, as rcl reads them."""
    path = tmp_path / "plugins.yaml"
    path.write_text(
        "/**:\n  ros__parameters:\n    mujoco_plugins:\n      cameras:\n"
        '        type: "mujoco_ros2_control_plugins/CameraPlugin"\n        camera_publish_rate: 6.0\n'
        "/**:\n  ros__parameters:\n"
        '    mujoco_plugins.lidars.type: "mujoco_ros2_control_plugins/RangefinderLidarPlugin"\n'
        "    mujoco_plugins.lidars.lidar_publish_rate: 12.0\n"
        "    mujoco_plugins.lidars.fan.topic: /scan\n"
        "/**:\n  ros__parameters: {mujoco_plugins: {cameras: {front: {frame_name: optical}}}}\n"
    )
    config = SensorConfig.load(path)
    assert (config.camera_rate, config.lidar_rate) == (6.0, 12.0)
    assert config.cameras["front"].frame_name == "optical" and config.rangefinder_lidars["fan"].topic == "/scan"
    assert config.warnings == []
    path.write_text("/**:\n  ros__parameters:\n    mujoco_plugins: [\n")
    with pytest.raises(SensorConfigError, match=rf"^{re.escape(str(path))}:4:1: malformed YAML: "):
        SensorConfig.load(path)


@pytest.mark.parametrize(
    "config, message",
    [
        ({"sensors": {"noise": {"slyde/*": {"stddev": 1}}}}, "noise pattern 'slyde/\\*' matches no state interface"),
        ({"sensors": {"noise": {"slide/position": {"sigma": 1}}}}, "unknown noise key 'sigma'"),
        ({"sensors": {"noise": {"slide/position": {"dropout": 0.1}}}}, "dropout is for depth and lidar ranges only"),
        ({"sensors": {"cameras": {"rear": {"width": 64}}}}, "camera 'rear' is not in the model"),
        ({"sensors": {"lidars": {"top": {"site": "nowhere", "horizontal": {"samples": 4, "max_angle": 1}}}}}, "no site 'nowhere'"),
        ({"sensors": {"camera_rate": -1}}, "camera_rate: must be > 0 Hz"),
        ({"sensors": {"rates": 1}}, "unknown key 'rates'"),
        ({"robot": {"ros__parameters": {"mujoco_plugins": {"x": {"update_rate": 1}}}}}, "a plugin needs a `type`"),
    ],
)
def test_bad_configuration_is_one_line_naming_the_key(config, message):
    sim = batchsim.make(str(SCENE), 1, "cpu")
    with pytest.raises(SensorConfigError, match=message) as e:
        sim.set_sensor_config(config)
    assert "\n" not in str(e.value)


def test_dense_lidar_from_yaml(tmp_path):
    config = {
        "sensors": {
            "lidars": {
                "ring": {
                    "site": "lidar",
                    "horizontal": {"samples": 9, "min_angle": -0.4, "max_angle": 0.4},
                    "vertical": {"samples": 2, "min_angle": 0.0, "max_angle": 0.1},
                    "range_max": 1.905,
                }
            }
        }
    }
    sim = batchsim.make(str(SCENE), 1, "cpu", sensors=config)
    sim.configure()
    ld = sim.sensors.lidar("ring")
    assert (ld.nrow, ld.ncol) == (2, 9)
    assert ld.topic == "ring/points"  # the scene's "cloud" would also take `points`: each gets its own
    ranges = sim.scan("ring")[0]
    # only the straight-ahead ray of the lower row (1.9 m) is within range_max; the next are 1.9095 m
    assert np.isfinite(ranges).sum() == 1 and abs(ranges[4] - WALL) < DEPTH_TOL
    sim.shutdown()


def test_lidar_element_in_a_ros2_control_file(tmp_path):
    xml = SCENE.read_text().replace(
        '<lidar ref_site="lidar" sensor_name="scan" min_angle="-0.5" max_angle="0.5" angle_increment="0.25" range_max="10"/>',
        "",
    )
    urdf = tmp_path / "robot.urdf"
    urdf.write_text(
        """<robot name="r">
  <ros2_control name="sim" type="system"><joint name="slide"><command_interface name="position"/>
    <state_interface name="position"/></joint></ros2_control>
  <mujoco_inputs><processed_inputs>
    <lidar ref_site="lidar" sensor_name="side" min_angle="1.0" max_angle="2.0" angle_increment="0.5"/>
  </processed_inputs></mujoco_inputs>
</robot>"""
    )
    spec = batchsim.model.load_string(xml, path=SCENE, ros2_control=urdf)
    ld = batchsim.sensors.SensorSuite.build(spec, 1).lidar("side")
    np.testing.assert_allclose(_angles(ld), [1.0, 1.5, 2.0])


@pytest.mark.parametrize(
    "element, message",
    [
        ('<lidar ref_site="lidar" sensor_name="x" min_angle="0" max_angle="1" angle_increment="0"/>', "angle_increment must be > 0"),
        ('<lidar ref_site="lidar" sensor_name="x" min_angle="0" max_angle="1"/>', "needs the attribute angle_increment"),
        ('<lidar ref_site="lidar" sensor_name="x" min_angle="0" max_angle="1" angle_increment="0.1" fov="1"/>', "unknown attribute 'fov'"),
    ],
)
def test_bad_lidar_element_is_a_model_error(element, message):
    xml = SCENE.read_text().replace("</mujoco>", element + "\n</mujoco>")
    with pytest.raises(ModelError, match=message):
        batchsim.model.load_string(xml, path=SCENE)


def test_cli_reports_a_bad_sensor_file_in_one_line(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("sensors:\n  noise:\n    nothing_here: {stddev: 1}\n")
    proc = subprocess.run(
        [sys.executable, "-m", "batchsim.cli", "--model", str(SCENE), "--worlds", "1", "--no-ros", "--sensors", str(bad)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"batchsim: error: {bad}: noise pattern 'nothing_here' matches no state interface, sensor, camera or lidar "
        "(e.g. slide/position, slide/velocity, slide/effort, slide_pos/position, slide_pos, fan-0, fan-1)"
    ]


def test_sensor_config_from_flags():
    assert SensorConfig.from_flags(None) is None
    config = SensorConfig.from_flags(None, camera_rate=30, camera_resolution="64x48", seed=3)
    assert (config.camera_rate, config.camera_resolution, config.seed) == (30.0, (64, 48), 3)
    with pytest.raises(SensorConfigError, match="--camera-resolution"):
        SensorConfig.from_flags(None, camera_resolution="64")


def test_host_site_poses_are_each_worlds_kinematics_at_its_current_state():
    """HostSensors.site_poses (threaded, for cpu and mjx lidars) gives what mj_kinematics gives per
    world, bit for bit, at the state rows as they are now (not the last step's kinematics)."""
    import mujoco
    from mujoco import batch as mjbatch

    from batchsim.backends.host_sensors import HostSensors

    sim = batchsim.make(str(SCENE), 1, "cpu")  # the scene's <lidar> elements: not plain MJCF
    m = sim.model
    sim.shutdown()
    batch = mjbatch.Batch(m, 5, nthread=2)
    batch.bind("qpos")[:] = np.random.default_rng(3).uniform(-0.5, 0.5, (5, m.nq))
    sensors = HostSensors(m, batch)
    d = mujoco.MjData(m)
    for worlds in (np.arange(5), np.array([4, 1])):
        for site in range(m.nsite):
            xpos, xmat = sensors.site_poses(site, worlds)
            for k, w in enumerate(worlds):
                batch.get_data(int(w), d)
                mujoco.mj_kinematics(m, d)
                assert np.array_equal(xpos[k], d.site_xpos[site]) and np.array_equal(xmat[k], d.site_xmat[site].reshape(3, 3))
    sensors.close()


@pytest.mark.slow  # over a few seconds: `make quick` leaves it out
def test_the_loop_profile_times_each_configuration_and_puts_the_library_back():
    """benchmarks/sensor_loop_profile.py (issue 24: mjx's camera loop), a short run on cpu: every
    configuration ran its periods, the phases land where they ran (the render thread, or the
    sampler when drawn in the loop), and the functions it timed are MuJoCo's and HostSensors'
    own again afterwards."""
    import argparse
    import importlib.util

    import mujoco

    from batchsim.backends.host_sensors import HostSensors

    folder = str(Path(__file__).resolve().parent.parent / "benchmarks")
    sys.path.insert(0, folder)  # the script imports its siblings by bare name
    try:
        spec = importlib.util.spec_from_file_location("_loop_profile", f"{folder}/sensor_loop_profile.py")
        profile = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(profile)
    finally:
        while folder in sys.path:
            sys.path.remove(folder)
    own = (mujoco.mjr_render, mujoco.mj_kinematics, HostSensors.submit, HostSensors.cast)
    args = argparse.Namespace(seconds=0.2, rounds=2, control_rate=100.0, camera_rate=10.0, lidar_rate=10.0)
    out = profile.profile("cpu", 2, (32, 24), args)
    configs = out["configs"]
    assert list(configs) == list(profile.CONFIGS) and out["budget_ms"] == pytest.approx(10.0)
    for name, c in configs.items():
        assert c["periods"] == 20 and c["rtf"] > 0, name
        period = c["ms"]["period"]
        assert 0 < period[0] <= period[1], name
    assert "lidar rays" not in configs["physics"]["ms"] and configs["physics"]["scans_per_s"] == 0
    assert configs["lidar"]["scans_per_s"] > 0 and configs["lidar"]["frames_per_s"] == 0
    both, sync = configs["camera+lidar"], configs["camera+lidar sync"]
    assert both["frames_per_s"] > 0 and "loop render: draw" not in both["ms"]  # drawn on the render thread
    assert sync["frames_per_s"] > 0 and "loop render: draw" in sync["ms"] and "render: draw" not in sync["ms"]
    assert sync["ms"]["drawing"][1] > 0
    assert (mujoco.mjr_render, mujoco.mj_kinematics, HostSensors.submit, HostSensors.cast) == own
