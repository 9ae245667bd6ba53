"""mujoco_ros2_control's BaseVelocityPlugin (batchsim.plugins.base_velocity) through the Python API, no ROS:
its params read from the plugin YAML, and the override on every backend.

The model is upstream's unit-test setup (test_base_velocity_plugin.cpp: a free body, no gravity)
with an arm on the base, damped and swung by a position actuator in every world, so that
something pushes the base the override has to hold. Three worlds start at yaws 0, 0.5 and
-1 rad; world 1 is commanded within the limits, world 2 beyond both (max_linear_velocity 1,
max_yaw_rate 0.5), world 0 nothing. Each backend's run is checked against what the plugin
does (the command held in the base's rotated frame, clamped, zero after cmd_timeout, the
other worlds untouched) and against a plain MuJoCo loop that does what
upstream's simulation does: the target rotated by the base's orientation at each control
update, written into qvel before every mj_step. The behaviour over ROS is
tests/test_mujoco_ros2_control_ros.py's (demo 05).
"""

from __future__ import annotations

import math
from pathlib import Path

import mujoco
import numpy as np
import pytest
from conftest import need

import batchsim
from batchsim.plugins.base_velocity import PLUGIN_TYPE
from batchsim.sensors import SensorConfig, SensorConfigError

DEMOS = Path(__file__).parent / "upstream" / "mujoco_ros2_control_demos"
MODEL = """
<mujoco model="base_velocity_test">
  <option timestep="0.002" gravity="0 0 0"/>
  <worldbody>
    <body name="base" pos="0 0 0.5">
      <freejoint name="base_joint"/>
      <geom type="box" size="0.2 0.15 0.05" mass="20"/>
      <body name="arm">
        <joint name="arm_joint" type="hinge" axis="0 0 1" damping="5"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.025" mass="2"/>
      </body>
    </body>
    <body name="welded" pos="1 0 0.5"><geom type="sphere" size="0.1"/></body>
  </worldbody>
  <actuator><position name="arm_joint" joint="arm_joint" kp="200"/></actuator>
</mujoco>
"""
LIMITS = {"max_linear_velocity": 1.0, "max_yaw_rate": 0.5}
SUBSTEPS, PERIODS, TIMEOUT = 10, 40, 0.5  # 0.8 s: the commands, sent at t = 0, expire at 0.5 s
YAW0 = np.array([0.0, 0.5, -1.0])
COMMANDS = {1: (0.4, 0.1, 0.0), 2: (3.0, 4.0, 2.0)}  # world 2: 5 m/s and 2 rad/s, beyond both limits
ARM = 0.6  # rad, every world's arm command
# The arm's push moves a held base by dt^2 * its acceleration in each substep, until the next
# substep's override: up to 4e-3 m or rad while the arm swings (the first SETTLED periods;
# without the override the base turns 0.075 rad), 2e-5 after it (measured on cpu)
SETTLED, KICK, LEAK = 10, 5e-3, 1e-4


def _plugin(**params) -> dict:
    return {"/**": {"ros__parameters": {"mujoco_plugins": {"base_velocity_plugin": {"type": PLUGIN_TYPE, **params}}}}}


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> str:
    path = tmp_path_factory.mktemp("base_velocity") / "base.xml"
    path.write_text(MODEL)
    return str(path)


def _yawed(qpos: np.ndarray) -> np.ndarray:
    qpos = qpos.copy()
    qpos[:, 3], qpos[:, 4:6], qpos[:, 6] = np.cos(YAW0 / 2), 0.0, np.sin(YAW0 / 2)
    return qpos


def _run(model: str, backend: str, plugin: bool = True) -> tuple[np.ndarray, np.ndarray, int, batchsim.BatchedSystem]:
    """qpos (PERIODS + 1, 3, nq) and qvel (PERIODS + 1, 3, nv) at each period's start, the number
    of periods that started within the timeout (sim time, summed step by step), and the system."""
    sim = batchsim.make(model, 3, backend, sensors=_plugin(body="base", **LIMITS) if plugin else None)
    sim.configure()
    sim.activate()
    qpos, qvel = sim.qstate()
    sim.set_qstate(None, _yawed(qpos), qvel)
    sim.command[:] = ARM
    out, fresh = [], 0
    for k in range(PERIODS):
        sim.read()
        out.append(sim.qstate())
        fresh += bool(sim.time[0] <= TIMEOUT)
        if k == 0 and plugin:
            sim.set_base_velocity([COMMANDS[1], COMMANDS[2]], worlds=[1, 2])
        sim.write()
        sim.step(SUBSTEPS)
    sim.read()
    out.append(sim.qstate())
    return np.stack([q for q, _ in out]), np.stack([v for _, v in out]), fresh, sim


def _reference(model: str) -> np.ndarray:
    """qpos (PERIODS + 1, 3, nq) from a plain MuJoCo loop per world, upstream's algorithm."""
    m = mujoco.MjModel.from_xml_path(model)
    out = np.zeros((PERIODS + 1, 3, m.nq))
    for w in range(3):
        d = mujoco.MjData(m)
        d.qpos[:] = _yawed(np.tile(d.qpos, (3, 1)))[w]
        mujoco.mj_forward(m, d)
        d.ctrl[:] = ARM
        vx, vy, wz = COMMANDS.get(w, (0.0, 0.0, 0.0))
        for k in range(PERIODS):
            out[k, w] = d.qpos
            if d.time > TIMEOUT:  # stale: zero velocity
                vx = vy = wz = 0.0
            speed = math.hypot(vx, vy)
            if speed > LIMITS["max_linear_velocity"]:
                vx, vy = vx * LIMITS["max_linear_velocity"] / speed, vy * LIMITS["max_linear_velocity"] / speed
            wz = min(max(wz, -LIMITS["max_yaw_rate"]), LIMITS["max_yaw_rate"])
            xmat = np.zeros(9)
            mujoco.mju_quat2Mat(xmat, d.qpos[3:7] / np.linalg.norm(d.qpos[3:7]))
            held = (xmat[0] * vx + xmat[1] * vy, xmat[3] * vx + xmat[4] * vy, wz)
            for _ in range(SUBSTEPS):
                d.qvel[[0, 1, 5]] = held
                mujoco.mj_step(m, d)
        out[PERIODS, w] = d.qpos
    return out


def _yaw(qpos: np.ndarray) -> np.ndarray:
    return 2 * np.arctan2(qpos[..., 6], qpos[..., 3])


_runs: dict[str, tuple[np.ndarray, np.ndarray, int, batchsim.BatchedSystem]] = {}


@pytest.fixture(scope="module")
def run(one_device_backend, model):
    if one_device_backend not in _runs:
        _runs[one_device_backend] = _run(model, one_device_backend)
    yield _runs[one_device_backend]


def test_the_command_is_held_in_the_rotated_frame_clamped_then_dropped(run):
    qpos, qvel, fresh, sim = run
    assert not sim.status.any()
    # t = 0.5 is 250 steps of 0.002 s, a little more than 0.5: stale (upstream's test: age <= cmd_timeout)
    assert fresh == 25
    t, dt = fresh * SUBSTEPS * sim.dt, SUBSTEPS * sim.dt
    yaw = _yaw(qpos)
    # while the arm swings, its push leaks into the held bases (0.075 rad without the override)
    turned = YAW0 + np.outer(np.arange(SETTLED) * dt, [0.0, 0.0, 0.5])  # world 2 turns at 0.5 rad/s
    assert np.abs(yaw[:SETTLED] - turned).max() < KICK and np.abs(qpos[:SETTLED, :, 2] - 0.5).max() < KICK
    # world 1: (0.4, 0.1) m/s in its frame, yawed 0.5 rad, not turning
    c, s = math.cos(0.5), math.sin(0.5)
    moved = qpos[fresh, 1, :2] - qpos[0, 1, :2]
    np.testing.assert_allclose(moved, t * np.array([c * 0.4 - s * 0.1, s * 0.4 + c * 0.1]), atol=LEAK)
    np.testing.assert_allclose(yaw[SETTLED : fresh + 1, 1], 0.5, atol=LEAK)
    # world 2: 1 m/s (5 asked, its direction kept) and 0.5 rad/s (2 asked)
    np.testing.assert_allclose(yaw[fresh, 2], -1.0 + 0.5 * t, atol=LEAK)
    step = np.diff(qpos[SETTLED : fresh + 1, 2, :2], axis=0)
    np.testing.assert_allclose(np.linalg.norm(step, axis=1), dt * 1.0, atol=LEAK)
    heading = np.arctan2(step[:, 1], step[:, 0]) - yaw[SETTLED:fresh, 2]  # each period's, from its start
    np.testing.assert_allclose(heading, math.atan2(4.0, 3.0), atol=1e-2)
    # world 0, never commanded, and every world after the timeout: held still
    np.testing.assert_allclose(qpos[SETTLED:, 0, :3], qpos[0, 0, :3][None].repeat(PERIODS + 1 - SETTLED, 0), atol=LEAK)
    np.testing.assert_allclose(yaw[SETTLED:, 0], 0.0, atol=LEAK)
    after = qpos[fresh + 1 :, :, :2]
    np.testing.assert_allclose(after, after[:1].repeat(len(after), 0), atol=LEAK)
    np.testing.assert_allclose(qvel[fresh + 1 :, :, [0, 1, 5]], 0.0, atol=LEAK)
    # the arm did swing: the override, not stillness, held the bases
    assert np.all(np.abs(qpos[-1, :, 7] - ARM) < 0.05)


def test_every_backend_runs_upstreams_algorithm(run, one_device_backend, model):
    qpos, _, _, _ = run
    # cpu to round-off (the rotation's arithmetic is not mju_quat2Mat's); mjx and warp in float32
    atol = 1e-12 if one_device_backend == "cpu" else 1e-4
    np.testing.assert_allclose(qpos, _reference(model), atol=atol)


def test_without_the_plugin_the_arm_turns_the_base(model):
    qpos, _, _, _ = _run(model, "cpu", plugin=False)
    assert abs(_yaw(qpos[-1, 0])) > 0.05  # -0.075 rad: what the override holds off


def test_reset_drops_a_worlds_command_and_no_other(model):
    sim = batchsim.make(model, 3, "cpu", sensors=_plugin(body="base"))
    sim.configure()
    sim.activate()
    sim.set_base_velocity([1.0, 0.0, 0.0])
    sim.write()
    sim.step(SUBSTEPS)
    sim.reset([1])
    assert sim.base_velocity.stamp[1] == -np.inf and sim.base_velocity.stamp[0] == 0.0
    start = sim.qstate()[0]
    sim.step(SUBSTEPS)  # no write(): world 1's override lifted, the others' still held
    qpos, qvel = sim.qstate()
    assert qpos[0, 0] - start[0, 0] == pytest.approx(SUBSTEPS * sim.dt) and qpos[1, 0] == start[1, 0]
    sim.read()
    sim.write()
    sim.step(SUBSTEPS)
    assert sim.qstate()[0][1, 0] == start[1, 0]  # held at zero: no command since its reset


def test_set_base_velocity_checks_what_it_is_given(model):
    sim = batchsim.make(model, 2, "cpu", sensors=_plugin(body="base"))
    sim.configure()
    with pytest.raises(ValueError, match=r"shape \(1, 3\) or \(3,\)"):
        sim.set_base_velocity([[1.0, 0.0]], worlds=[0])
    with pytest.raises(ValueError, match="finite"):
        sim.set_base_velocity([np.nan, 0.0, 0.0])
    with pytest.raises(ValueError, match="out of range"):
        sim.set_base_velocity([0.0, 0.0, 0.0], worlds=[2])
    plain = batchsim.make(model, 1, "cpu")
    assert plain.base_velocity is None
    with pytest.raises(ValueError, match="no BaseVelocityPlugin"):
        plain.set_base_velocity([0.0, 0.0, 0.0])


def test_the_demos_plugin_yaml_is_read():
    config = SensorConfig.load(DEMOS / "config" / "mujoco_ros2_control_plugins_base_velocity.yaml")
    assert config.warnings == []
    bv = config.base_velocity
    assert (bv.name, bv.body, bv.cmd_vel_topic, bv.use_stamped_twist) == ("base_velocity_plugin", "base_link", "/cmd_vel", False)
    assert (bv.max_linear_velocity, bv.max_yaw_rate, bv.cmd_timeout) == (math.inf, math.inf, 0.5)  # upstream's defaults


@pytest.mark.parametrize(
    "params, message",
    [
        ({}, r"base_velocity_plugin\.body: required"),
        ({"body": "b", "max_speed": 1}, r"base_velocity_plugin: unknown key 'max_speed'"),
        ({"body": "b", "max_yaw_rate": -1.0}, r"base_velocity_plugin\.max_yaw_rate: must be a number >= 0"),
        ({"body": "b", "cmd_timeout": "1"}, r"base_velocity_plugin\.cmd_timeout: must be a number"),
        ({"body": "b", "use_stamped_twist": "yes"}, r"base_velocity_plugin\.use_stamped_twist: must be true or false"),
        ({"body": "b", "cmd_vel_topic": "~/cmd_vel"}, r"base_velocity_plugin\.cmd_vel_topic: '~/cmd_vel' is not a topic"),
    ],
)  # fmt: skip
def test_a_bad_param_is_one_line_naming_the_key(params, message):
    with pytest.raises(SensorConfigError, match=message) as e:
        SensorConfig.load(_plugin(**params))
    assert "\n" not in str(e.value) and str(e.value).startswith("<sensor config>: /**.ros__parameters.mujoco_plugins.")


def test_a_body_without_a_free_joint_fails_at_make(model):
    with pytest.raises(batchsim.ConfigurationError, match=r"base_velocity_plugin\.body: no body 'chassis'.*bodies: base"):
        batchsim.make(model, 1, "cpu", sensors=_plugin(body="chassis"))
    with pytest.raises(batchsim.ConfigurationError, match=r"\.body: body 'welded' has no free joint"):
        batchsim.make(model, 1, "cpu", sensors=_plugin(body="welded"))


def test_a_fleet_over_several_devices_refuses_it(model):
    need("mujoco_warp")
    with pytest.raises(batchsim.ConfigurationError, match="not run on a fleet spread over several devices"):
        batchsim.make(model, 2, "warp", devices=["cpu", "cpu"], sensors=_plugin(body="base"))


def test_the_bridge_takes_each_worlds_cmd_vel_under_its_namespace(model):
    from batchsim.controllers.topics import MessageKind
    from ros_bridge.naming import topic_name
    from ros_bridge.options import BridgeOptions
    from ros_bridge.plan import build_plan

    sim = batchsim.make(model, 2, "cpu", sensors=_plugin(body="base", cmd_vel_topic="/cmd_vel", use_stamped_twist=True))
    sim.configure()
    plan, _, inputs = build_plan(sim, 100.0, BridgeOptions(tf=False), None, 1)
    (spec,) = [s for s in plan.inputs if s.controller == "base_velocity_plugin"]
    assert spec.kind is MessageKind.TWIST_STAMPED and spec.width == 7
    assert [topic_name(ns, spec.topic) for ns in plan.namespaces] == ["/world_0/cmd_vel", "/world_1/cmd_vel"]
    one = batchsim.make(model, 1, "cpu", sensors=_plugin(body="base"))
    one.configure()
    root, _, _ = build_plan(one, 100.0, BridgeOptions(namespace="", tf=False), None, 1)
    assert topic_name(root.namespaces[0], root.inputs[-1].topic) == "/cmd_vel"
    # a TwistStamped row (linear xyz, angular xyz, stamp): linear.x, linear.y, angular.z taken; NaN refused
    rows = np.array([[0.1, 0.2, 9.0, 9.0, 9.0, 0.3, 5.0], [np.nan, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
    refused = inputs[plan.inputs.index(spec)].apply(np.array([1, 0]), rows)
    assert [k for k, _ in refused] == [1] and "finite" in refused[0][1]
    np.testing.assert_array_equal(sim.base_velocity.command, [[0.0, 0.0, 0.0], [0.1, 0.2, 0.3]])
    assert sim.base_velocity.stamp.tolist() == [-np.inf, 0.0]  # the sim time it came, not the message's stamp
