"""Several robots in one world (batchsim.fleet): composition, the contract on every backend,
parity with raw mj_step, contacts between robots, per-robot controllers, and bad fleet files."""

from __future__ import annotations

import math
import tarfile
from pathlib import Path

import mujoco
import numpy as np
import pytest
from conftest import need

import batchsim
from batchsim import FleetError, Status
from batchsim.controllers.robots import load_fleet_controllers
from batchsim.fleet import load_fleet, read_fleet, robot_view
from batchsim.fleet.view import OTHER
from batchsim.loop import SimLoop

ROBOTS = Path(__file__).resolve().parents[2] / "shared" / "robots"
TWO_ARMS = {
    "robots": [
        {"name": "arm_a", "model": "arm", "pose": [0.0, 0.0, 0.0, 0.0]},
        {"name": "arm_b", "model": "arm", "pose": [1.5, 0.0, 0.0, math.pi]},
    ]
}
ARM_AND_ROVER = {
    "robots": [
        {"name": "arm", "model": "arm", "pose": [0.0, 0.0, 0.0, 0.0]},
        {"name": "amr", "model": "rover", "pose": [0.0, 2.0, 0.0, math.pi / 2]},
    ]
}


@pytest.fixture(scope="module")
def menagerie(tmp_path_factory) -> Path:
    """The shared Menagerie robots, unpacked."""
    if not ROBOTS.is_dir():
        pytest.skip(f"{ROBOTS} is not beside the checkout")
    root = tmp_path_factory.mktemp("menagerie")
    for archive in ("universal_robots_ur5e", "unitree_go2"):
        with tarfile.open(ROBOTS / f"{archive}.tar.xz") as tar:
            tar.extractall(root, filter="data")
    return root


def active(model, backend: str, nworld: int = 4) -> batchsim.BatchedSystem:
    sim = batchsim.make(model, nworld, backend)
    sim.configure()
    sim.activate()
    return sim


# ---------------------------------------------------------------- composition


def test_two_copies_of_one_model_are_two_robots_with_their_own_names_and_columns():
    spec = load_fleet(TWO_ARMS)
    alone = batchsim.load("arm")
    assert [r.name for r in spec.robots] == ["arm_a", "arm_b"]
    assert spec.command_interfaces == [f"arm_a/{n}" for n in alone.command_interfaces] + [
        f"arm_b/{n}" for n in alone.command_interfaces
    ]
    for r in spec.robots:
        assert [spec.state_interfaces[c] for c in r.state] == [r.prefix + n for n in alone.state_interfaces]
        assert [spec.command_interfaces[c] for c in r.commands] == [r.prefix + n for n in alone.command_interfaces]
        assert set(r.sensors) == {r.prefix + s.name for s in alone.sensors}
        first, n = r.bodies
        assert all(spec.mjmodel.body(b).name.startswith(r.prefix) for b in range(first, first + n))
    # the robot's own scene (the arm file's floor and light) is left out: the world has one floor
    m = spec.mjmodel
    floors = [m.geom(g).name for g in range(m.ngeom) if m.geom(g).name.endswith("floor")]
    assert floors == ["floor"]


def test_each_robot_starts_in_its_own_keyframe_at_its_pose(menagerie):
    spec = load_fleet(
        {
            "robots": [
                {"name": "ur", "model": str(menagerie / "universal_robots_ur5e/scene.xml"), "pose": [0, 0, 0, 0]},
                {"name": "dog", "model": str(menagerie / "unitree_go2/scene.xml"), "pose": [1.0, 2.0, 0.0, math.pi / 2]},
            ]
        }
    )
    ur, dog = batchsim.load(menagerie / "universal_robots_ur5e/scene.xml"), batchsim.load(menagerie / "unitree_go2/scene.xml")
    r_ur, r_dog = spec.robots
    q = spec.initial.qpos
    n_ur = ur.mjmodel.nq
    assert np.allclose(q[:n_ur], ur.initial.qpos)  # the UR5e's `home`
    base = r_dog.floating_base
    assert base is not None and base.body == "dog/base"
    # the Go2's `home` puts its base 0.27 m up; the fleet pose carries it to (1, 2) turned 90 degrees
    assert np.allclose(q[base.qposadr : base.qposadr + 3], [1.0, 2.0, dog.initial.qpos[2]])
    assert np.allclose(q[base.qposadr + 3 : base.qposadr + 7], [math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)])
    assert np.allclose(q[base.qposadr + 7 :], dog.initial.qpos[7:])
    # the UR5e's keyframe gives ctrl, so its commands start there; the Go2's motors start at 0
    sim = active(spec, "cpu", 1)
    assert np.allclose(sim.command[0, r_ur.commands], ur.initial.ctrl)
    assert spec.initial.source == "ur: keyframe 'home'; dog: keyframe 'home'"
    sim.shutdown()


def test_a_robot_view_names_only_its_own_joints_and_sensors_locally():
    spec = load_fleet(ARM_AND_ROVER)
    arm, amr = spec.robots
    view = robot_view(spec, amr)
    assert [j.name for j in view.joints] == ["left_wheel_joint", "right_wheel_joint"]
    assert len(view.state) == len(spec.state)  # the world's columns, so indices stay the world's
    assert view.state_interfaces[amr.state[0]] == spec.state_interfaces[amr.state[0]].removeprefix("amr/")
    # the arm's are out of the rover's reach: no name its YAML gives finds them
    assert view.state_interfaces[arm.state[0]] == OTHER + spec.state_interfaces[arm.state[0]]
    assert view.floating_base is not None and view.floating_base.body == "base"


# ---------------------------------------------------------------- the contract, on every backend


def test_the_contract_on_a_world_of_two_robots(backend):
    sim = active(TWO_ARMS, backend)
    a, b = sim.spec.robots
    n = 4
    assert sim.state.shape == (n, len(sim.export_state_interfaces()))
    assert sim.command.shape == (n, 12)
    names = sim.export_state_interfaces()
    pos_a, pos_b = names.index("arm_a/joint1/position"), names.index("arm_b/joint1/position")
    sim.command[:, a.commands[0]] = 0.4  # arm_a's joint1 only
    sim.command[:, b.commands[0]] = -0.2
    for _ in range(40):
        sim.write()
        sim.step(10)
    sim.read()
    assert np.allclose(sim.state[:, pos_a], 0.4, atol=0.03)
    assert np.allclose(sim.state[:, pos_b], -0.2, atol=0.03)
    before = sim.state.copy()
    sim.reset(worlds=[1, 3])
    assert np.array_equal(sim.state[[0, 2]], before[[0, 2]])
    assert np.allclose(sim.state[[1, 3], pos_a], 0.0) and np.allclose(sim.state[[1, 3], pos_b], 0.0)
    # a NaN in one robot's row of one world: that world's command is refused, no other's
    sim.command[2, b.commands[1]] = np.nan
    sim.write()
    assert sim.status[2] & Status.BAD_COMMAND and not (np.delete(sim.status, 2) & Status.BAD_COMMAND).any()
    sim.shutdown()


def test_cpu_world_of_robots_equals_raw_mj_step_of_its_model():
    sim = active(ARM_AND_ROVER, "cpu", 2)
    m = sim.spec.mjmodel
    d = mujoco.MjData(m)
    sim.spec.initial.apply(m, d)
    rng = np.random.default_rng(3)
    for _ in range(20):
        command = rng.uniform(-0.5, 0.5, sim.command.shape[1])
        sim.command[:] = command
        sim.write()
        d.ctrl[[c.actuator_id for c in sim.spec.commands]] = command
        sim.step(5)
        for _ in range(5):
            mujoco.mj_step(m, d)
    qpos, qvel = sim.qstate([1])
    assert np.array_equal(qpos[0], d.qpos) and np.array_equal(qvel[0], d.qvel)
    sim.shutdown()


def test_a_robot_in_a_world_of_robots_moves_as_it_does_alone():
    """Two arms that never touch: each follows the trajectory the arm alone follows."""
    world, alone = active(TWO_ARMS, "cpu", 1), active("arm", "cpu", 1)
    b = world.spec.robots[1]
    target = np.linspace(-0.3, 0.3, 6)
    world.command[0, b.commands] = target
    alone.command[0] = target
    for _ in range(30):
        for sim in (world, alone):
            sim.write()
            sim.step(10)
            sim.read()
    assert np.allclose(world.state[0, b.state], alone.state[0], atol=1e-6)
    world.shutdown()
    alone.shutdown()


def test_robots_driven_into_each_other_stop_with_contact_force():
    fleet = {
        "robots": [
            {"name": "left", "model": "rover", "pose": [0.0, 0.0, 0.0, 0.0]},
            {"name": "right", "model": "rover", "pose": [1.2, 0.0, 0.0, math.pi]},
        ]
    }
    sim = active(fleet, "cpu", 1)
    manager = load_fleet_controllers(sim.spec, 1)
    loop = SimLoop(sim, control_rate=100, rtf=0, participants=[manager])
    for _ in range(400):  # 4 s, both driving forward at each other (cmd_vel times out after 0.5 s)
        for name in ("left", "right"):
            manager[f"{name}/diff_drive_controller"].set_cmd_vel(0, 0.6, 0.0)
        loop.run_period()
    spec, m = sim.spec, sim.spec.mjmodel
    left, right = (r.floating_base for r in spec.robots)
    qpos, qvel = sim.qstate([0])
    gap = qpos[0, right.qposadr] - qpos[0, left.qposadr]
    assert 0.3 < gap < 0.6, gap  # 2.4 m of driving would have crossed them: they met and stopped
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = qpos[0], qvel[0]
    mujoco.mj_forward(m, d)
    force = np.zeros(6)
    touching = 0.0
    for i in range(d.ncon):
        c = d.contact[i]
        b1, b2 = int(m.geom_bodyid[c.geom1]), int(m.geom_bodyid[c.geom2])
        names = {m.body(b1).name.split("/")[0], m.body(b2).name.split("/")[0]}
        if names == {"left", "right"}:
            mujoco.mj_contactForce(m, d, i, force)
            touching = max(touching, abs(force[0]))
    assert touching > 0.1
    sim.shutdown()


# ---------------------------------------------------------------- per-robot controllers


def test_each_robot_has_its_own_controllers_and_a_goal_moves_only_its_robot():
    sim = active(TWO_ARMS, "cpu", 2)
    manager = load_fleet_controllers(sim.spec, 2)
    assert "arm_a/joint_trajectory_controller" in manager.controllers
    jtc_b = manager["arm_b/joint_trajectory_controller"]
    assert jtc_b.command_interfaces[0] == "arm_b/joint1/position"
    loop = SimLoop(sim, control_rate=100, rtf=0, duration=1.0, participants=[manager])
    joints = [f"joint{k}" for k in range(1, 7)]
    jtc_b.set_trajectory(1, joints, [0.5], [[0.3, 0.2, 0.1, 0.0, 0.0, 0.0]])
    loop.run()
    a, b = sim.spec.robots
    names = sim.export_state_interfaces()
    j1 = names.index("arm_b/joint1/position")
    assert abs(sim.state[1, j1] - 0.3) < 0.02
    assert abs(sim.state[0, j1]) < 0.01  # the other world
    assert np.abs(sim.state[:, a.state[:6:3]]).max() < 0.01 or np.abs(sim.state[:, [names.index(f"arm_a/joint{k}/position") for k in range(1, 7)]]).max() < 0.01
    # switching robot b's trajectory controller off in world 1 touches nothing of robot a's
    result = manager.switch([1], deactivate=["arm_b/joint_trajectory_controller"])
    assert result.ok
    assert manager.active("arm_a/joint_trajectory_controller").all()
    assert list(manager.active("arm_b/joint_trajectory_controller")) == [True, False]
    sim.shutdown()


def test_a_controllers_file_naming_a_joint_the_robot_lacks_names_the_robot(tmp_path):
    yaml_file = tmp_path / "amr.yaml"
    yaml_file.write_text(
        "controller_manager:\n  ros__parameters:\n    update_rate: 100\n"
        "    fwd:\n      type: forward_command_controller/ForwardCommandController\n"
        "fwd:\n  ros__parameters:\n    joints: [joint1]\n    interface_name: position\n"
    )
    fleet = {"robots": [{"name": "amr", "model": "rover", "controllers": str(yaml_file)}, {"name": "arm", "model": "arm", "pose": [2, 0, 0]}]}
    sim = batchsim.make(fleet, 1, "cpu")
    with pytest.raises(batchsim.ConfigurationError, match=r"robot amr.*joint1"):
        load_fleet_controllers(sim.spec, 1)


# ---------------------------------------------------------------- bad fleet files


@pytest.mark.parametrize(
    "text, match",
    [
        ("robots:\n  - {name: a, model: arm}\n  - {name: a, model: arm, pose: [2, 0, 0]}\n", r"robots\[1\]: the name 'a' is taken by robots\[0\]"),
        ("robots:\n  - {name: 3arm, model: arm}\n", r"robots\[0\]\.name: '3arm' is not a valid ROS name"),
        ("robots:\n  - {name: a}\n", r"robots\[0\]: model is missing"),
        ("robots:\n  - {name: a, model: arm, count: 0}\n", r"robots\[0\]\.count: a whole number of robots, at least 1, got 0"),
        ("robots:\n  - {name: a, model: arm, speed: 3}\n", r"robots\[0\]\.speed: unknown key"),
        ("robots:\n  - {name: a, model: arm, pose: [1, 2]}\n", r"robots\[0\]\.pose: \[x, y, z, yaw\]"),
        ("robots: []\n", r"robots: a list of at least one robot"),
        ("robots:\n  - {name: a, model: arm, controllers: nowhere.yaml}\n", r"robots\[0\]\.controllers: no such file"),
        ("robots:\n  - {name: 'a_{k}', model: rover, count: 3}\n", r"3 robots need a placement rule"),
        ("robots: [\n", r"fleet.yaml:\d+:\d+: malformed YAML"),
    ],
)
def test_a_bad_fleet_file_is_one_line_naming_the_file_and_key(tmp_path, text, match):
    path = tmp_path / "fleet.yaml"
    path.write_text(text)
    with pytest.raises(FleetError, match=match) as e:
        read_fleet(path)
    assert str(path) in str(e.value) and "\n" not in str(e.value)


def test_a_missing_model_names_the_robot(tmp_path):
    path = tmp_path / "fleet.yaml"
    path.write_text("robots:\n  - {name: a, model: arm}\n  - {name: b, model: nosuch.xml, pose: [2, 0, 0]}\n")
    with pytest.raises(FleetError, match=r"robots\[1\] \(b\): \S*nosuch.xml: no such file"):
        load_fleet(path)


def test_a_grid_that_places_robots_into_each_other_is_refused(tmp_path):
    path = tmp_path / "fleet.yaml"
    path.write_text("robots:\n  - {name: 'amr_{k}', model: rover, count: 2, grid: {spacing: [0.2, 1.0], columns: 2}}\n")
    with pytest.raises(FleetError, match=r"robots\[0\]\.grid: its spacing places amr_1 and amr_2 overlap"):
        load_fleet(path)


def test_robots_placed_by_hand_into_each_other_are_a_warning_naming_both_and_the_depth():
    spec = load_fleet({"robots": [{"name": "a", "model": "rover"}, {"name": "b", "model": "rover", "pose": [0.1, 0, 0]}]})
    overlap = [w for w in spec.warnings if "overlap" in w]
    assert overlap and "robots a and b overlap at their start pose by" in overlap[0] and " mm " in overlap[0]


# ---------------------------------------------------------------- random placement per world

RANDOM_CARTS = {
    "robots": [
        {"name": "arm", "model": "arm"},
        {"name": "cart_{k}", "model": "rover", "count": 4, "random": {"area": [1.0, -2.0, 4.0, 2.0], "min_distance": 0.8}},
    ]
}


def _cart_positions(sim) -> np.ndarray:
    sim.read()
    return sim.base_states[:, :, :2].copy()


def test_robots_placed_at_random_differ_per_world_keep_apart_and_repeat_by_world_number():
    sim = active(RANDOM_CARTS, "cpu", 4)
    xy = _cart_positions(sim)
    assert not np.allclose(xy[0], xy[1])
    assert ((xy >= [1.0, -2.0]) & (xy <= [4.0, 2.0])).all()
    for w in range(4):
        gaps = np.linalg.norm(xy[w][:, None] - xy[w][None], axis=-1) + np.eye(4) * 9
        assert gaps.min() >= 0.8
    sim.reset([2])  # a reset keeps the world's draw (redraw_on_reset is the randomization's)
    assert np.allclose(_cart_positions(sim), xy)
    sim.shutdown()
    alone = batchsim.make(RANDOM_CARTS, 1, "cpu", world_offset=2)  # world 2, reproduced alone
    alone.configure()
    assert np.allclose(_cart_positions(alone)[0], xy[2])
    alone.shutdown()


def test_a_random_rule_for_a_fixed_base_or_too_small_an_area_is_refused():
    fixed = {"robots": [{"name": "a_{k}", "model": "arm", "count": 2, "random": {"area": [0, 0, 5, 5]}}]}
    with pytest.raises(FleetError, match=r"robots\[0\]\.random: places a robot by its free joint, and a_1 \(arm\) has a fixed base"):
        load_fleet(fixed)
    crowded = {"robots": [{"name": "c_{k}", "model": "rover", "count": 20, "random": {"area": [0, 0, 2, 2], "min_distance": 1.0}}]}
    with pytest.raises(FleetError, match=r"robots\[0\]\.random: 20 robots 1 m apart do not fit in 2 x 2 m"):
        read_fleet(crowded)


def test_a_controllers_file_for_a_robot_not_in_the_world_is_refused_naming_the_key(tmp_path):
    arm_yaml = Path(batchsim.controllers.default_controllers("arm")).read_text()
    namespaced = tmp_path / "arms.yaml"  # written for a robot amr_9, given to arm_b
    namespaced.write_text(arm_yaml.replace("controller_manager:", "/amr_9/controller_manager:", 1))
    fleet = {"robots": [{"name": "arm_a", "model": "arm"}, {"name": "arm_b", "model": "arm", "pose": [2, 0, 0], "controllers": str(namespaced)}]}
    sim = batchsim.make(fleet, 1, "cpu")
    with pytest.raises(batchsim.ConfigurationError, match=r"/amr_9/controller_manager: names the namespace 'amr_9' \(no robot of the world\)"):
        load_fleet_controllers(sim.spec, 1)
    own = tmp_path / "arm_b.yaml"  # its own namespace is fine
    own.write_text(arm_yaml.replace("controller_manager:", "/arm_b/controller_manager:", 1))
    fleet["robots"][1]["controllers"] = str(own)
    manager = load_fleet_controllers(batchsim.make(fleet, 1, "cpu").spec, 1)
    assert "arm_b/joint_trajectory_controller" in manager.controllers


def test_the_vector_env_shows_a_world_of_several_robots_as_one_world():
    need("gymnasium")
    import batchsim.vector

    env = batchsim.vector.make(ARM_AND_ROVER, 3, "cpu")
    obs, _ = env.reset(seed=0)
    sim = env.sim
    assert env.single_action_space.shape == (len(sim.spec.commands),)  # every robot's commands
    obs, reward, terminated, truncated, _ = env.step(np.zeros((3, *env.single_action_space.shape)))
    assert obs.shape[0] == 3 and np.isfinite(obs).all()
    env.close()


def test_a_reset_of_one_robot_restores_only_it_in_only_that_world():
    from batchsim.fleet.reset import reset_robot

    sim = active(ARM_AND_ROVER, "cpu", 3)
    arm, rover = sim.spec.robots
    sim.command[:, arm.commands] = 0.4
    sim.command[:, rover.commands] = 1.0  # wheel torques: the rovers drive off
    for _ in range(50):
        sim.write()
        sim.step(10)
    qpos, qvel = sim.qstate()
    reset_robot(sim, rover, [1])
    after, after_v = sim.qstate()
    q0, nq = rover.qpos
    assert np.allclose(after[1, q0 : q0 + nq], sim.spec.initial.qpos[q0 : q0 + nq])  # the rover is home
    assert np.array_equal(np.delete(after[1], np.s_[q0 : q0 + nq]), np.delete(qpos[1], np.s_[q0 : q0 + nq]))  # the arm is not
    assert np.array_equal(after[[0, 2]], qpos[[0, 2]]) and np.array_equal(after_v[[0, 2]], qvel[[0, 2]])
    assert np.allclose(sim.command[1, rover.commands], 0.0) and np.allclose(sim.command[1, arm.commands], 0.4)
    assert np.allclose(sim.command[[0, 2]][:, rover.commands], 1.0)
    sim.shutdown()


def test_each_robots_lidar_publishes_under_its_own_namespace_as_it_alone_would():
    one = batchsim.make({"robots": [{"name": "amr", "model": "rover"}]}, 1, "cpu")
    assert one.sensors.lidars["amr/base_scan"].topic == "amr/scan"  # not the world's `scan`
    two = batchsim.make({"robots": [{"name": "a", "model": "rover"}, {"name": "b", "model": "rover", "pose": [2, 0, 0]}]}, 1, "cpu")
    assert [ld.topic for ld in two.sensors.lidars.values()] == ["a/scan", "b/scan"]
    assert batchsim.make("rover", 1, "cpu").sensors.lidars["base_scan"].topic == "scan"


def test_a_robot_whose_elements_hang_on_its_files_static_bodies_is_refused_in_one_line(tmp_path):
    """A fleet leaves a robot file's static bodies out with its scene; a weld to a mocap handle
    there went silently (and sensors on such sites gave an IndexError)."""
    robot = tmp_path / "welded.xml"
    robot.write_text(
        '<mujoco model="r"><worldbody>'
        '<body name="handle" mocap="true" pos="0 0 1"><geom type="sphere" size="0.02" contype="0" conaffinity="0"/></body>'
        '<body name="link" pos="0 0 0.5"><joint name="j" type="hinge" axis="0 1 0"/>'
        '<geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03"/></body></worldbody>'
        '<equality><weld body1="handle" body2="link"/></equality><actuator><motor name="j" joint="j"/></actuator></mujoco>'
    )
    with pytest.raises(FleetError, match=r"robots\[0\] \(w\): its 1 equality refer to bodies or sites of \S+welded.xml that hold no joint"):
        load_fleet({"robots": [{"name": "w", "model": str(robot)}]})


# ---------------------------------------------------------------- a robot's own sensors file

#: rover a's file: its camera at its own size and topic, noise on its wheels' positions
OWN_CAMERA_AND_NOISE = """sensors:
  cameras:
    front_camera: {width: 64, height: 48, image_topic: cam/rgb, frame_name: /cam_optical}
  noise:
    "*_wheel_joint/position": {stddev: 0.01}
"""


def two_rovers(tmp_path, a: str | None, b: str | None) -> dict:
    """A fleet of rovers `a` and `b`, each with its own sensors file where given (its text)."""
    robots = []
    for name, text, pose in (("a", a, [0, 0, 0]), ("b", b, [2, 0, 0])):
        robot = {"name": name, "model": "rover", "pose": pose}
        if text is not None:
            (tmp_path / f"{name}.yaml").write_text(text)
            robot["sensors"] = str(tmp_path / f"{name}.yaml")
        robots.append(robot)
    return {"robots": robots}


def noisy(sim) -> list[str]:
    """The state interfaces read() puts noise on."""
    sim.write()
    sim.step(5)
    sim.read()
    return [sim.spec.state[c].name for c in np.flatnonzero((sim.state != sim.true_state).any(axis=0))]


def test_each_robots_own_sensors_file_gives_it_what_the_file_asks_and_the_other_robot_nothing(tmp_path):
    """Issue 43: `sensors:` under a robot was refused (a robot's own sensors file is not
    applied yet); now each file applies to its robot, named as the world names it."""
    fleet = two_rovers(tmp_path, OWN_CAMERA_AND_NOISE, "sensors:\n  camera_resolution: [32, 24]\n")
    assert [r.sensors for r in read_fleet(fleet).robots] == [tmp_path / "a.yaml", tmp_path / "b.yaml"]
    sim = active(fleet, "cpu", 2)
    cams = sim.sensors.cameras
    assert {n: (c.width, c.height) for n, c in cams.items()} == {"a/front_camera": (64, 48), "b/front_camera": (32, 24)}
    a, b = cams["a/front_camera"], cams["b/front_camera"]
    # a's topic and frame under its namespace, as alone under the world's; b's its defaults
    assert (a.image_topic, a.depth_topic, a.frame_id) == ("a/cam/rgb", "a/front_camera/depth/image_raw", "a/cam_optical")
    assert (b.image_topic, b.frame_id) == ("b/front_camera/image_raw", "b/front_camera")
    assert noisy(sim) == ["a/left_wheel_joint/position", "a/right_wheel_joint/position"]  # b's wheels: none
    assert [ld.topic for ld in sim.sensors.lidars.values()] == ["a/scan", "b/scan"]
    assert sim.render("b/front_camera").rgb.shape == (2, 24, 32, 3)
    sim.shutdown()


def test_a_robots_file_gives_it_in_a_fleet_what_it_gives_it_alone(tmp_path):
    (tmp_path / "amr.yaml").write_text(OWN_CAMERA_AND_NOISE)
    alone = batchsim.make("rover", 2, "cpu", sensors=tmp_path / "amr.yaml")
    alone.configure()
    alone.activate()
    fleet = two_rovers(tmp_path, OWN_CAMERA_AND_NOISE, None)
    sim = active(fleet, "cpu", 2)
    mine, theirs = alone.sensors.camera("front_camera"), sim.sensors.camera("a/front_camera")
    assert (theirs.width, theirs.height) == (mine.width, mine.height) == (64, 48)
    assert theirs.info == mine.info  # the intrinsics
    assert (sim.sensors.camera("b/front_camera").width, sim.sensors.camera("b/front_camera").height) == (320, 240)
    names = noisy(alone)
    assert noisy(sim) == ["a/" + n for n in names] and names == ["left_wheel_joint/position", "right_wheel_joint/position"]
    # one seed, one stream over the noisy values: the fleet's first robot draws what it draws alone
    columns = [sim.spec.state_interfaces.index("a/" + n) for n in names]
    own = [alone.spec.state_interfaces.index(n) for n in names]
    assert np.array_equal(sim.state[:, columns] - sim.true_state[:, columns], alone.state[:, own] - alone.true_state[:, own])
    alone.shutdown()
    sim.shutdown()


def test_the_whole_fleets_sensors_are_laid_over_each_robots_own(tmp_path):
    """`sensors=` (`--sensors`) names the world's cameras; it wins where both set a key."""
    fleet = two_rovers(tmp_path, OWN_CAMERA_AND_NOISE, "sensors:\n  camera_resolution: [32, 24]\n  camera_rate: 7\n")
    user = {"sensors": {"camera_resolution": [16, 12], "cameras": {"a/front_camera": {"height": 20}}, "camera_rate": 9}}
    sim = batchsim.make(fleet, 1, "cpu", sensors=user)
    # a's own width beats the fleet's size as a camera's own width beats --camera-resolution alone
    assert {n: (c.width, c.height) for n, c in sim.sensors.cameras.items()} == {"a/front_camera": (64, 20), "b/front_camera": (16, 12)}
    assert sim.sensors.camera_rate == 9.0
    assert batchsim.make(fleet, 1, "cpu").sensors.camera_rate == 7.0  # b's, the world's one rate
    assert any("camera_rate 7 is the world's" in w and "a takes it too" in w for w in load_fleet(fleet).sensor_config.warnings)


def test_the_command_line_applies_each_robots_file_under_the_fleets(tmp_path):
    from batchsim.cli import runner
    from batchsim.cli.args import run_parser

    (tmp_path / "a.yaml").write_text(OWN_CAMERA_AND_NOISE)
    (tmp_path / "fleet.yaml").write_text(
        "robots:\n  - {name: a, model: rover, sensors: a.yaml}\n  - {name: b, model: rover, pose: [2, 0, 0]}\n"
    )
    (tmp_path / "all.yaml").write_text("sensors:\n  cameras:\n    b/front_camera: {width: 100}\n")
    argv = ["--fleet", str(tmp_path / "fleet.yaml"), "--worlds", "1", "--backend", "cpu", "--no-ros"]
    for extra, sizes in (([], [(64, 48), (320, 240)]), (["--sensors", str(tmp_path / "all.yaml")], [(64, 48), (100, 240)])):
        sim = runner.build(run_parser().parse_args(argv + extra))
        assert [(c.width, c.height) for c in sim.sensors.cameras.values()] == sizes
        sim.shutdown()


def test_a_robots_plugins_move_under_its_prefix_and_one_per_world(tmp_path):
    plugin = (
        "/**:\n  ros__parameters:\n    mujoco_plugins:\n      base_velocity_plugin:\n"
        "        type: mujoco_ros2_control_plugins/BaseVelocityPlugin\n        body: base\n        cmd_vel_topic: /cmd_vel\n"
    )
    sim = batchsim.make(two_rovers(tmp_path, None, plugin), 1, "cpu")
    sim.configure()
    config = sim.base_velocity.config
    assert (config.body, config.cmd_vel_topic) == ("b/base", "b/cmd_vel")  # b's base, on /world_3/b/cmd_vel
    sim.shutdown()
    with pytest.raises(FleetError, match=r"robots\[0\]\.sensors \(a\): \S+a\.yaml: /\*\*\.ros__parameters\.mujoco_plugins\."
                       r"base_velocity_plugin and robots\[1\]\.sensors \(b\): \S+b\.yaml: \S+ each ask for a BaseVelocityPlugin"):
        load_fleet(two_rovers(tmp_path, plugin, plugin))


@pytest.mark.parametrize(
    "text, message",
    [
        ("sensors:\n  cameras:\n    rear_camera: {width: 64}\n", r"a\.yaml: camera 'rear_camera' is not in the model \(cameras: front_camera\)"),
        ("sensors:\n  noise:\n    'arm_joint*': {stddev: 0.1}\n", r"a\.yaml: noise pattern 'arm_joint\*' matches no state interface"),
        ("sensors:\n  lidars:\n    top: {site: mast, horizontal: {samples: 4, max_angle: 1}}\n", r"sensors\.lidars\.top: the model has no site 'mast'"),
        ("/**:\n  ros__parameters:\n    mujoco_plugins:\n      l: {type: mujoco_ros2_control_plugins/Mujoco3dLidarPlugin, scan: {topic: s}}\n",
         r"mujoco_3d_lidar_plugin sensor 'scan' is not in the model \(lidar plugin sensors: base_scan\)"),
        ("/**:\n  ros__parameters:\n    mujoco_plugins:\n      v: {type: mujoco_ros2_control_plugins/BaseVelocityPlugin, body: chassis}\n",
         r"mujoco_plugins\.v\.body: no body 'chassis' in the model \(bodies: base, left_wheel, right_wheel\)"),
        ("sensors: [\n", r"a\.yaml:2:1: malformed YAML"),
        (b"sensors:\n  seed: \xff\n", r"a\.yaml: not a text file \(byte 0xff at offset 17 is not UTF-8\)"),
    ],
)
def test_a_bad_robot_sensors_file_is_one_line_naming_its_file_and_key(tmp_path, text, message):
    path = tmp_path / "a.yaml"
    path.write_bytes(text) if isinstance(text, bytes) else path.write_text(text)
    fleet = {"robots": [{"name": "a", "model": "rover", "sensors": str(path)}]}
    with pytest.raises(FleetError, match=r"^<fleet>: robots\[0\]\.sensors \(a\): .*" + message) as e:
        batchsim.make(fleet, 1, "cpu")
    assert "\n" not in str(e.value)


def test_robots_files_that_set_a_worlds_one_setting_apart_are_refused_naming_both(tmp_path):
    with pytest.raises(FleetError, match=r"robots\[0\]\.sensors \(a\): \S+a\.yaml sets seed 1 and robots\[1\]\.sensors \(b\): "
                       r"\S+b\.yaml sets seed 2: a world has one noise seed"):
        load_fleet(two_rovers(tmp_path, "sensors:\n  seed: 1\n", "sensors:\n  seed: 2\n"))


def test_a_camera_of_the_robot_files_scene_is_named_as_left_out(tmp_path):
    robot = tmp_path / "r.xml"
    robot.write_text(
        '<mujoco model="r"><worldbody><camera name="overview" pos="0 0 3"/>'
        '<body name="link"><joint name="j" type="hinge"/><geom type="sphere" size="0.1"/></body></worldbody>'
        '<actuator><motor name="j" joint="j"/></actuator></mujoco>'
    )
    (tmp_path / "s.yaml").write_text("sensors:\n  cameras:\n    overview: {width: 32}\n")
    with pytest.raises(FleetError, match=r"robots\[0\]\.sensors \(w\): \S+s\.yaml: camera 'overview' is on a body of \S+r\.xml "
                       "that holds no joint, which a fleet leaves out"):
        load_fleet({"robots": [{"name": "w", "model": str(robot), "sensors": str(tmp_path / "s.yaml")}]})


def test_a_robots_controllers_cannot_name_another_robots_joint(tmp_path):
    """`b/joint1` in robot a's YAML was taken: a's broadcaster published b's joint, and a
    forward command controller gave a KeyError (found by a review)."""
    arm_yaml = Path(batchsim.controllers.default_controllers("arm")).read_text()
    path = tmp_path / "a.yaml"
    path.write_text(arm_yaml + "joint_state_broadcaster:\n  ros__parameters:\n    joints: [joint1, b/joint1]\n")
    fleet = {"robots": [{"name": "a", "model": "arm", "controllers": str(path)}, {"name": "b", "model": "arm", "pose": [2, 0, 0]}]}
    with pytest.raises(batchsim.ConfigurationError, match=r"b/joint1"):
        load_fleet_controllers(batchsim.make(fleet, 1, "cpu").spec, 1)


def test_a_robots_reset_drops_its_controllers_goals_only():
    """ControllerManager.reset_robot (what `<ns>/<robot>/reset` runs beside reset_robot): robot a's
    trajectory in world 0 is dropped, robot b's in world 0 and robot a's in world 1 run on."""
    from batchsim.fleet.reset import reset_robot

    sim = active(TWO_ARMS, "cpu", 2)
    manager = load_fleet_controllers(sim.spec, 2)
    loop = SimLoop(sim, control_rate=100, rtf=0, participants=[manager])
    joints = [f"joint{k}" for k in range(1, 7)]
    for robot in ("arm_a", "arm_b"):
        for w in (0, 1):
            manager[f"{robot}/joint_trajectory_controller"].set_trajectory(w, joints, [2.0], [[0.6, 0, 0, 0, 0, 0]])
    for _ in range(20):
        loop.run_period()
    a = sim.spec.robots[0]
    reset_robot(sim, a, [0])
    manager.reset_robot(sim, "arm_a", [0])
    for _ in range(200):
        loop.run_period()
    names = sim.export_state_interfaces()
    j1 = {r: names.index(f"{r}/joint1/position") for r in ("arm_a", "arm_b")}
    assert abs(sim.state[0, j1["arm_a"]]) < 0.02  # its goal dropped: held where the reset put it
    assert abs(sim.state[0, j1["arm_b"]] - 0.6) < 0.03 and abs(sim.state[1, j1["arm_a"]] - 0.6) < 0.03
    sim.shutdown()
