"""mujoco_ros2_control's ExternalWrenchPlugin (batchsim.plugins.external_wrench) through the Python API, no
ROS: its params read from the plugin YAML, the wrenches on every backend, the loop's side of the
apply_wrench service (ros_bridge/simulation.py) and the service's names in the bridge's plan.

The model is upstream's unit-test body (test_external_wrench_plugin.cpp: a free body, no
gravity), made a box whose centre of mass is off its frame's origin and which starts tilted, with
a damped flap hinged to it, so that the body-frame rotation and the transport to the CoM both
matter. World 1 gets two wrenches at once (one ramped down, one of zero duration on the flap), then
worlds 1 and 2 one more each (a row per world); world 0 none. Each backend's run is checked
against a plain MuJoCo loop that does upstream's update at every control period (xfrc_applied
zeroed, each running wrench rotated by the body's xmat and transported to its xipos, expired
ones dropped) before its mj_steps. The behaviour over ROS is tests/test_external_wrench_ros.py's.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest
from conftest import need

import batchsim
from batchsim.plugins.external_wrench import PLUGIN_TYPE, ExternalWrench, ExternalWrenches
from batchsim.sensors import SensorConfig, SensorConfigError

DEMOS = Path(__file__).parent / "upstream" / "mujoco_ros2_control_demos"
MODEL = """
<mujoco model="external_wrench_test">
  <option timestep="0.002" gravity="0 0 0"/>
  <worldbody>
    <body name="box" pos="0 0 1" euler="0.3 -0.2 0.5">
      <freejoint name="box_joint"/>
      <geom type="box" size="0.2 0.1 0.05" pos="0.05 0.02 0" mass="2"/>
      <body name="flap" pos="0.25 0.02 0">
        <joint name="hinge" type="hinge" axis="0 0 1" damping="0.05"/>
        <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.02" mass="0.3"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""
SUBSTEPS, PERIODS = 10, 25  # 0.02 s periods, 0.5 s
# (period, worlds, wrench): durations end between two control updates, so that no backend's
# clock rounding decides which update is the last
A = ExternalWrench("box", (3.0, 0.0, 1.0), (0.0, 0.2, 0.0), (0.1, 0.05, 0.0), duration=0.155, ramp_down=0.05)
B = ExternalWrench("flap", (0.0, 1.0, 0.0), point=(0.2, 0.0, 0.0))  # zero duration: one update
C = ExternalWrench("box", [[0.0, 0.0, 2.0], [1.0, 1.0, 0.0]], (0.1, 0.0, 0.0), duration=[0.05, 0.295])
SCHEDULE = [(0, [1], [A, B]), (3, [1, 2], [C])]


def _plugin(name: str = "external_wrench", **params) -> dict:
    return {"/**": {"ros__parameters": {"mujoco_plugins": {name: {"type": PLUGIN_TYPE, **params}}}}}


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> str:
    path = tmp_path_factory.mktemp("external_wrench") / "box.xml"
    path.write_text(MODEL)
    return str(path)


def _run(model: str, backend: str) -> tuple[np.ndarray, np.ndarray, list, batchsim.BatchedSystem]:
    """qpos (PERIODS + 1, 3, nq), qvel (PERIODS + 1, 3, nv) at each period's start, whether each
    request still ran after each write(), and the system."""
    sim = batchsim.make(model, 3, backend, sensors=_plugin())
    sim.configure()
    sim.activate()
    out, running, requests = [], [], []
    for k in range(PERIODS):
        sim.read()
        out.append(sim.qstate())
        for period, worlds, wrenches in SCHEDULE:
            if period == k:
                requests.append(sim.apply_wrench(wrenches, worlds))
        sim.write()
        running.append(sim.wrench_running(requests).tolist())
        sim.step(SUBSTEPS)
    sim.read()
    out.append(sim.qstate())
    return np.stack([q for q, _ in out]), np.stack([v for _, v in out]), running, sim


def _rows(value, worlds: list[int], w: int, width: int | None) -> np.ndarray:
    array = np.asarray(value, float)
    return array[worlds.index(w)] if array.ndim == (2 if width else 1) else array


def _reference(model: str) -> tuple[np.ndarray, np.ndarray]:
    """qpos and qvel as _run's, from a plain MuJoCo loop per world: upstream's update."""
    m = mujoco.MjModel.from_xml_path(model)
    qpos, qvel = np.zeros((PERIODS + 1, 3, m.nq)), np.zeros((PERIODS + 1, 3, m.nv))
    for w in range(3):
        d = mujoco.MjData(m)
        mujoco.mj_forward(m, d)
        active = []
        for k in range(PERIODS):
            qpos[k, w], qvel[k, w] = d.qpos, d.qvel
            for period, worlds, wrenches in SCHEDULE:
                if period == k and w in worlds:
                    for e in wrenches:
                        active.append(
                            dict(
                                body=mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, e.body),
                                force=_rows(e.force, worlds, w, 3),
                                torque=_rows(e.torque, worlds, w, 3),
                                point=_rows(e.point, worlds, w, 3),
                                end=d.time + float(_rows(e.duration, worlds, w, None)),
                                ramp=float(_rows(e.ramp_down, worlds, w, None)),
                            )
                        )
            # ExternalWrenchPlugin::update, after the hardware interface zeroed xfrc_applied
            d.xfrc_applied[:] = 0.0
            now = d.time
            for a in active:
                scale = 1.0
                if a["ramp"] > 0 and a["end"] - now < a["ramp"]:
                    scale = max(0.0, (a["end"] - now) / a["ramp"])
                b = a["body"]
                xmat = d.xmat[b].reshape(3, 3)
                point_world = d.xpos[b] + xmat @ a["point"]
                force_world = xmat @ (a["force"] * scale)
                torque_world = xmat @ (a["torque"] * scale)
                d.xfrc_applied[b, :3] += force_world
                d.xfrc_applied[b, 3:] += torque_world + np.cross(point_world - d.xipos[b], force_world)
            active = [a for a in active if not now >= a["end"]]
            for _ in range(SUBSTEPS):
                mujoco.mj_step(m, d)
        qpos[PERIODS, w], qvel[PERIODS, w] = d.qpos, d.qvel
    return qpos, qvel


_runs: dict[str, tuple] = {}


@pytest.fixture(scope="module")
def run(one_device_backend, model):
    if one_device_backend not in _runs:
        _runs[one_device_backend] = _run(model, one_device_backend)
    yield _runs[one_device_backend]


def test_every_backend_runs_upstreams_algorithm(run, one_device_backend, model):
    qpos, qvel, _, sim = run
    assert not sim.status.any()
    ref_qpos, ref_qvel = _reference(model)
    assert np.linalg.norm(ref_qvel[-1, 1:, :3], axis=1).min() > 0.05  # the wrenches did push worlds 1 and 2
    # cpu to round-off (the rotation's arithmetic is not mju_quat2Mat's); mjx and warp in float32
    atol = 1e-10 if one_device_backend == "cpu" else 1e-4
    np.testing.assert_allclose(qpos, ref_qpos, atol=atol)
    np.testing.assert_allclose(qvel, ref_qvel, atol=atol * 10)


def test_durations_and_other_worlds(run):
    qpos, qvel, running, sim = run
    # A ends at 0.155 s: applied at the updates of 0, 0.02, ..., 0.16 s (the 9th drops it); B at
    # the first only; C at 0.06 .. 0.12 s in world 1 and 0.06 .. 0.36 s in world 2
    assert [r[0] for r in running] == [True] * 8 + [False] * (PERIODS - 8)
    assert [r[1] for r in running[3:]] == [True] * 15 + [False] * (PERIODS - 18)
    assert sim.external_wrenches.count == 0
    # world 0 had none: where it started, still (float32 on mjx and warp)
    np.testing.assert_allclose(qpos[:, 0], qpos[:1, 0].repeat(PERIODS + 1, 0), atol=1e-6)
    np.testing.assert_allclose(qvel[:, 0], 0.0, atol=1e-6)
    # world 2's first was at period 3: untouched before, and by world 1's wrenches
    np.testing.assert_allclose(qpos[:4, 2], qpos[:1, 2].repeat(4, 0), atol=1e-6)


def test_the_update_scales_rotates_and_transports():
    store = ExternalWrenches()
    rows = dict(
        world=np.array([0, 0]), body=np.array([1, 1]), force=np.array([[2.0, 0, 0], [0, 0, 1.0]]),
        torque=np.array([[0, 0, 0.5], [0, 0, 0]]), point=np.array([[0, 1.0, 0], [0, 0, 0]]),
        end=np.array([1.0, 5.0]), ramp_down=np.array([0.5, 0.0]), request=np.array([1, 2]),
    )  # fmt: skip
    store.add(**rows)
    quarter = np.array([[np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]] * 2)  # 90 degrees about z
    ipos = np.array([[0.0, 0.5, 0.0]] * 2)
    for now, scale in ((0.0, 1.0), (0.6, 0.8), (0.9, 0.2), (1.2, 0.0)):
        out = np.zeros((1, 2, 6))
        store.xfrc(np.array([now]), quarter, ipos, out, np.array([0, 0]))
        # the first: body x is world y; its point 0.5 m along body y from the CoM, i.e. world -x
        f = 2.0 * scale * np.array([0.0, 1.0, 0.0])
        torque = 0.5 * scale * np.array([0, 0, 1.0]) + np.cross([-0.5, 0.0, 0.0], f)
        torque += np.cross([0.5, 0.0, 0.0], [0.0, 0.0, 1.0])  # the second: z at the origin, 0.5 m along x from the CoM
        np.testing.assert_allclose(out[0, 1], [*(f + [0, 0, 1.0]), *torque], atol=1e-12)
    store.expire(np.array([1.0]))
    assert store.request.tolist() == [2]  # now >= end: dropped


def test_reset_drops_a_worlds_wrenches_and_no_other(model):
    sim = batchsim.make(model, 3, "cpu")
    sim.configure()
    sim.activate()
    request = sim.apply_wrench(ExternalWrench("box", (5.0, 0.0, 0.0), duration=1.0))
    sim.read()
    sim.write()
    sim.step(SUBSTEPS)
    sim.reset([1])
    assert sorted(sim.external_wrenches.world.tolist()) == [0, 2] and sim.wrench_running(request)
    start = sim.qstate()[0]
    sim.step(SUBSTEPS)  # no write(): world 1's xfrc_applied went with its reset, the others' stay
    qpos = sim.qstate()[0]
    assert np.array_equal(qpos[1], start[1]) and not np.allclose(qpos[0], start[0])
    sim.reset()
    assert sim.external_wrenches.count == 0 and not sim.wrench_running(request)


def test_a_request_is_checked_whole_before_anything_is_applied(model):
    sim = batchsim.make(model, 2, "cpu")
    sim.configure()
    with pytest.raises(ValueError, match=r"^Body 'cube9' not found in MuJoCo model\.$"):
        sim.apply_wrench([ExternalWrench("box", (1.0, 0.0, 0.0)), ExternalWrench("cube9")])
    assert sim.external_wrenches is None  # nothing applied, not even the first
    with pytest.raises(ValueError, match=r"wrench 0 \('box'\): force must have shape \(3,\) or \(2, 3\)"):
        sim.apply_wrench(ExternalWrench("box", [[1.0, 0.0]]))
    with pytest.raises(ValueError, match=r"Wrench 0 \('box'\): torque must be finite"):
        sim.apply_wrench(ExternalWrench("box", torque=(np.nan, 0.0, 0.0)))
    with pytest.raises(ValueError, match="out of range"):
        sim.apply_wrench(ExternalWrench("box"), worlds=[2])
    assert sim.external_wrenches is None
    empty = sim.apply_wrench([])
    assert sim.external_wrenches is None and not sim.wrench_running(empty)


def test_the_loop_answers_at_once_and_marks_the_request_done_after_its_wrenches_ran(model):
    """ros_bridge/simulation.py: the host's side of apply_wrench, the shared marks in a dict."""
    from batchsim.loop import SimLoop
    from ros_bridge.protocol.requests import WRENCH_SLOTS, wrench_done
    from ros_bridge.simulation import SimulationRequests

    sim = batchsim.make(model, 2, "cpu")
    sim.configure()
    sim.activate()
    loop = SimLoop(sim, control_rate=50.0, rtf=0.0)
    memory = {"wrench.done": np.zeros((1, WRENCH_SLOTS), np.int64)}
    answers, woken = [], []
    requests = SimulationRequests(sim, loop, lambda *a: answers.append(a), memory, woken.append)
    entry = {"body": "box", "force": [0.0, 0.0, 4.0], "torque": [0.0] * 3, "point": [0.0] * 3, "duration": 0.09, "ramp_down": 0.0}
    requests.apply_wrench(0, 7, 1, {"wrenches": [entry, {**entry, "body": "cube9"}]})
    assert answers[-1][2:] == (0.0, False, "Body 'cube9' not found in MuJoCo model.")
    requests.apply_wrench(0, 8, 1, {"wrenches": [entry]})
    assert answers[-1][1:] == (8, 0.0, True, "Applied 1 wrench(es) successfully.")
    done_at = None
    while done_at is None:
        requests.poll()
        if wrench_done(memory, 0, 8):
            done_at = loop.sim_time
        else:
            loop.run_period()
    # applied at the updates of 0 .. 0.1 s (now >= end drops it after the 6th), marked after that period
    assert done_at == pytest.approx(0.12) and woken == [0] and not wrench_done(memory, 0, 7)
    qpos = sim.qstate()[0]
    assert qpos[0, 2] == 1.0 and qpos[1, 2] > 1.0  # world 1 pushed up, world 0 untouched


def test_the_bridge_serves_apply_wrench_under_each_worlds_namespace(model):
    from ros_bridge.interfaces import available
    from ros_bridge.naming import topic_name
    from ros_bridge.options import BridgeOptions
    from ros_bridge.plan import build_plan

    if not available()["mujoco_ros2_control_msgs"]:
        pytest.skip("mujoco_ros2_control_msgs is not built")
    sim = batchsim.make(model, 2, "cpu", sensors=_plugin("pusher"))
    sim.configure()
    plan, _, _ = build_plan(sim, 100.0, BridgeOptions(tf=False), None, 1)
    names = [topic_name(ns, plan.wrench_service) for ns in plan.namespaces]
    assert names == ["/world_0/pusher/apply_wrench", "/world_1/pusher/apply_wrench"]
    assert "wrench.done" in plan.layout
    one = batchsim.make(model, 1, "cpu", sensors=_plugin())
    one.configure()
    root, _, _ = build_plan(one, 100.0, BridgeOptions(namespace="", tf=False), None, 1)
    assert topic_name(root.namespaces[0], root.wrench_service) == "/external_wrench/apply_wrench"  # upstream's example
    plain = batchsim.make(model, 1, "cpu")
    plain.configure()
    assert build_plan(plain, 100.0, BridgeOptions(tf=False), None, 1)[0].wrench_service == ""


def test_the_plugin_yaml_is_read():
    config = SensorConfig.load(_plugin(force_arrow_scale=0.02))
    assert config.warnings == []
    w = config.external_wrench
    assert (w.name, w.service, w.force_arrow_scale, w.torque_arrow_scale) == ("external_wrench", "external_wrench/apply_wrench", 0.02, 0.1)


@pytest.mark.parametrize(
    "name, params, message",
    [
        ("external_wrench", {"arrow_scale": 1}, r"external_wrench: unknown key 'arrow_scale'"),
        ("external_wrench", {"torque_arrow_scale": "big"}, r"external_wrench\.torque_arrow_scale: must be a finite number"),
        ("2push", {}, r"2push: '2push' cannot name the plugin's sub-node"),
    ],
)  # fmt: skip
def test_a_bad_param_is_one_line_naming_the_key(name, params, message):
    with pytest.raises(SensorConfigError, match=message) as e:
        SensorConfig.load(_plugin(name, **params))
    assert "\n" not in str(e.value) and str(e.value).startswith("<sensor config>: /**.ros__parameters.mujoco_plugins.")
    two = {"/**": {"ros__parameters": {"mujoco_plugins": {"a": {"type": PLUGIN_TYPE}, "b": {"type": PLUGIN_TYPE}}}}}
    with pytest.raises(SensorConfigError, match=r"mujoco_plugins\.b: a second ExternalWrenchPlugin .*batchsim runs one"):
        SensorConfig.load(two)


def test_a_fleet_over_several_devices_refuses_it(model):
    need("mujoco_warp")
    with pytest.raises(batchsim.ConfigurationError, match="ExternalWrenchPlugin is not run on a fleet spread over several devices"):
        batchsim.make(model, 2, "warp", devices=["cpu", "cpu"], sensors=_plugin())


def test_the_command_line_runs_it_and_a_bad_param_stops_it_in_one_line(tmp_path):
    plugins = tmp_path / "plugins.yaml"
    plugins.write_text(f'/**:\n  ros__parameters:\n    mujoco_plugins:\n      pusher:\n        type: "{PLUGIN_TYPE}"\n')
    urdf = DEMOS / "demo_resources" / "robot" / "test_robot.urdf"
    cli = [sys.executable, "-m", "batchsim.cli"]
    done = subprocess.run([*cli, "info", "--ros2-control", str(urdf), "--sensors", str(plugins)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert "external wrench plugin pusher: service <ns>/pusher/apply_wrench" in done.stdout
    assert "ExternalWrenchPlugin" not in done.stdout.partition("warnings")[2]  # run, not warned of
    plugins.write_text(plugins.read_text() + "        force_arrow_scale: [1]\n")
    args = ["--ros2-control", str(urdf), "--sensors", str(plugins), "--no-ros", "--quiet", "--duration", "0.1"]
    done = subprocess.run([*cli, *args], capture_output=True, text=True)
    assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
    assert done.stderr.startswith(f"batchsim: error: {plugins}: /**.ros__parameters.mujoco_plugins.pusher.force_arrow_scale: ")
