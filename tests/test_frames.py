"""Body poses from the simulation (`BatchedSystem.body_poses`), the tf tree of a model
(batchsim/model/frames.py) and the robot_description generated from the MJCF
(batchsim/model/urdf.py), on the shipped models and on a Menagerie arm with meshes."""

from __future__ import annotations

import importlib.util
import os
import tarfile
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np
import pytest
from conftest import BACKENDS

import batchsim
from batchsim.model.frames import frame_tree, initial_transforms, relative_transforms
from batchsim.model.urdf import generate_urdf, robot_description, rpy

SHARED = Path(__file__).resolve().parents[2] / "shared" / "robots"
EXACT = 1e-9  # float64 round-off of a few compositions


@pytest.fixture(scope="module")
def ur5e(tmp_path_factory) -> Path:
    """The Menagerie UR5e (meshes, a home keyframe), unpacked: its scene.xml."""
    archive = SHARED / "universal_robots_ur5e.tar.xz"
    if not archive.is_file():
        pytest.skip(f"{archive} is absent (../shared holds the Menagerie robots; CI has it)")
    out = tmp_path_factory.mktemp("robots")
    with tarfile.open(archive) as tar:
        tar.extractall(out, filter="data")
    return out / "universal_robots_ur5e" / "scene.xml"


@pytest.fixture
def mesh_cache(tmp_path, monkeypatch) -> Path:
    """Generated meshes go to a cache of the test's own (not for the device backends' tests:
    Warp keeps its compiled kernels under XDG_CACHE_HOME too)."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    return tmp_path / "cache"


def _model(name: str, ur5e_path: Path | None = None) -> str:
    return str(ur5e_path) if name == "ur5e" else name


def _stepped(model: str, backend: str = "cpu", nworld: int = 2, periods: int = 3, **options):
    """An active system, body_poses() asked for once at the start, then `periods` periods of 5
    steps with a different command per world; returns it and each world's qpos before its last step."""
    sim = batchsim.make(model, nworld, backend, **options)
    sim.configure()
    sim.activate()
    sim.body_poses()  # from here on the engine keeps them (cpu binds xpos/xquat)
    rng = np.random.default_rng(0)
    sim.read()
    start = sim.state[0, : sim.command.shape[1]].copy() if sim.command.shape[1] else None
    for _ in range(periods):
        if start is not None:
            sim.command[:] = start + 0.2 * rng.standard_normal(sim.command.shape)
        sim.write()
        sim.step(5)
    return sim


def _kinematics(m: mujoco.MjModel, qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_kinematics(m, d)
    return d.xpos.copy(), d.xquat.copy()


# ---------------------------------------------------------------- body_poses on cpu


@pytest.mark.parametrize("model", ["arm", "quadruped", "humanoid"])
def test_cpu_body_poses_are_mujocos_kinematics_of_the_state_before_the_last_step(model):
    sim = _stepped(model)
    qpos = sim.device_arrays()["qpos"].copy()
    sim.step(1)
    xpos, xquat = sim.body_poses()
    m = sim.model
    assert xpos.shape == (2, m.nbody, 3) and xquat.shape == (2, m.nbody, 4)
    assert xpos.dtype == xquat.dtype == np.float64
    for w in range(2):
        ref_pos, ref_quat = _kinematics(m, qpos[w])
        np.testing.assert_allclose(xpos[w], ref_pos, rtol=0, atol=1e-12)
        np.testing.assert_allclose(xquat[w], ref_quat, rtol=0, atol=1e-12)
    # worlds in the order asked for, arrays of the caller's own
    some_pos, _ = sim.body_poses([1, 0])
    np.testing.assert_array_equal(some_pos, xpos[::-1])
    some_pos[:] = 0
    assert sim.body_poses()[0].any()
    sim.shutdown()


def test_cpu_first_call_after_steps_shows_the_current_state():
    sim = batchsim.make("arm", 2, "cpu")
    sim.configure()
    sim.command[:] = 0.5
    sim.activate()
    sim.write()
    sim.step(20)
    qpos = sim.device_arrays()["qpos"].copy()
    xpos, _ = sim.body_poses()  # nothing bound until now: the current qpos's kinematics, this once
    np.testing.assert_allclose(xpos[1], _kinematics(sim.model, qpos[1])[0], atol=1e-12)
    sim.reset([0])  # world 0 is filled by the reset, world 1 still by kinematics
    xpos, _ = sim.body_poses()
    d = mujoco.MjData(sim.model)
    sim.spec.initial.apply(sim.model, d)
    np.testing.assert_allclose(xpos[0], d.xpos, atol=1e-12)
    np.testing.assert_allclose(xpos[1], _kinematics(sim.model, qpos[1])[0], atol=1e-12)
    sim.shutdown()


def test_a_frozen_world_shows_the_poses_it_last_showed(tmp_path):
    from test_contract import CALM, SUBSTEPS, UNSTABLE

    path = tmp_path / "unstable.xml"
    path.write_text(UNSTABLE)
    sim = batchsim.make(str(path), 3, "cpu")
    sim.configure()
    sim.activate()
    sim.command[:] = 0.0
    for _ in range(CALM):
        sim.write()
        sim.step(SUBSTEPS)
    shown_pos, shown_quat = sim.body_poses()
    sim.command[1] = 1e9
    sim.write()
    sim.step(SUBSTEPS)
    assert sim.status[1] & batchsim.Status.DIVERGED
    for _ in range(2):
        sim.step(SUBSTEPS)
        into = np.zeros((3, sim.model.nbody, 7))
        sim.body_poses_into(into[..., :3], into[..., 3:])  # tf's copy: the same held poses
        xpos, xquat = sim.body_poses()
        np.testing.assert_array_equal(xpos[1], shown_pos[1])
        np.testing.assert_array_equal(xquat[1], shown_quat[1])
        assert np.isfinite(xpos).all() and not np.array_equal(xpos[0], shown_pos[0])  # the others move on
        np.testing.assert_array_equal(into[..., :3], xpos)
        np.testing.assert_array_equal(into[..., 3:], xquat)
    sim.reset([1])
    d = mujoco.MjData(sim.model)
    sim.spec.initial.apply(sim.model, d)
    np.testing.assert_array_equal(sim.body_poses([1])[0][0], d.xpos)
    sim.shutdown()


def test_body_poses_need_a_configured_system():
    sim = batchsim.make("arm", 1, "cpu")
    with pytest.raises(batchsim.LifecycleError, match="read body poses"):
        sim.body_poses()


# ---------------------------------------------------------------- the frame tree


@pytest.mark.parametrize("model", ["arm", "quadruped", "humanoid", "ur5e"])
def test_relative_transforms_compose_back_to_every_world_pose(model, ur5e):
    sim = _stepped(_model(model, ur5e), periods=2)
    xpos, xquat = sim.body_poses()
    tree = frame_tree(sim.spec)
    t, r = relative_transforms(tree, xpos, xquat)
    assert t.shape == (2, tree.nframe, 3) and r.shape == (2, tree.nframe, 4)
    np.testing.assert_allclose(np.linalg.norm(r, axis=-1), 1.0, atol=EXACT)
    # walk down from the root: the world pose of each frame from its parent's and the transform
    pos = {0: np.zeros((2, 3))}
    quat = {0: np.tile([1.0, 0.0, 0.0, 0.0], (2, 1))}
    for k, (body, parent) in enumerate(zip(tree.body, tree.parent_body, strict=True)):
        q_rel = r[:, k, [3, 0, 1, 2]]  # back to w, x, y, z
        pos[body] = np.empty((2, 3))
        quat[body] = np.empty((2, 4))
        for w in range(2):
            rotated = np.empty(3)
            mujoco.mju_rotVecQuat(rotated, t[w, k], quat[parent][w])
            pos[body][w] = pos[parent][w] + rotated
            mujoco.mju_mulQuat(quat[body][w], quat[parent][w], q_rel[w])
    end = tree.body[-1]  # the end link (the tool of the arm)
    np.testing.assert_allclose(pos[end], xpos[:, end], atol=EXACT)
    for body in tree.body:
        np.testing.assert_allclose(pos[body], xpos[:, body], atol=EXACT)
        same = np.abs(np.sum(quat[body] * xquat[:, body], axis=-1))  # q and -q: one rotation
        np.testing.assert_allclose(same, 1.0, atol=EXACT)
    # static frames hold in every state: what the initial state gives, once
    t0, r0 = initial_transforms(tree, sim.spec)
    np.testing.assert_allclose(
        t[:, tree.static], np.broadcast_to(t0[tree.static], t[:, tree.static].shape), atol=EXACT
    )
    np.testing.assert_allclose(np.abs(np.sum(r[:, tree.static] * r0[tree.static], axis=-1)), 1.0, atol=EXACT)
    sim.shutdown()


def test_arm_frames_static_and_moving():
    tree = frame_tree(batchsim.load("arm"))
    assert tree.root == "world"
    assert tree.names == ("base", "link1", "link2", "link3", "link4", "link5", "link6", "tool")
    assert tree.parents == ("world", "base", "link1", "link2", "link3", "link4", "link5", "link6")
    static = dict(zip(tree.names, tree.static, strict=True))
    assert static == {"base": True, "tool": True, **{f"link{i}": False for i in range(1, 7)}}


def test_a_floating_base_hangs_from_odom_and_moves():
    spec = batchsim.load("quadruped")
    tree = frame_tree(spec)
    assert tree.root == "odom"
    assert tree.frame(0) == "odom" and tree.names[0] == spec.floating_base.body == "base"
    assert tree.parents[0] == "odom" and not tree.static[0]
    assert tree.parents[tree.names.index("FL_hip")] == "base"


def test_unnamed_bodies_get_frames_of_their_id():
    m = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body name='a'><joint type='hinge'/><geom size='.1'/>"
        "<body pos='0 0 1'><geom size='.1'/></body></body></worldbody></mujoco>"
    )
    tree = frame_tree(m)
    assert tree.names == ("a", "body_2") and tree.parents == ("world", "a")
    assert list(tree.static) == [False, True]


# ---------------------------------------------------------------- robot_description


def _check_urdf(text: str, m: mujoco.MjModel) -> ET.Element:
    """A small URDF sanity check: named links, joints between links that exist, one tree."""
    root = ET.fromstring(text)
    assert root.tag == "robot"
    links = [link.get("name") for link in root.findall("link")]
    assert len(set(links)) == len(links)
    children = []
    for joint in root.findall("joint"):
        assert joint.get("type") in ("revolute", "continuous", "prismatic", "fixed", "floating")
        parent, child = joint.find("parent").get("link"), joint.find("child").get("link")
        assert parent in links and child in links, joint.get("name")
        children.append(child)
    assert len(set(children)) == len(children), "a link with two parents"
    roots = set(links) - set(children)
    assert len(roots) == 1, roots
    return root


def _urdf_poses(root: ET.Element) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Every link's pose with every joint at zero, from the joints' origins."""
    origin = {}
    for joint in root.findall("joint"):
        o = joint.find("origin")
        quat = np.empty(4)
        roll, pitch, yaw = (float(v) for v in o.get("rpy").split())
        rz, ry, rx = np.empty(4), np.empty(4), np.empty(4)
        mujoco.mju_axisAngle2Quat(rz, [0, 0, 1], yaw)
        mujoco.mju_axisAngle2Quat(ry, [0, 1, 0], pitch)
        mujoco.mju_axisAngle2Quat(rx, [1, 0, 0], roll)
        mujoco.mju_mulQuat(quat, rz, ry)
        mujoco.mju_mulQuat(quat, quat, rx)
        xyz = np.array([float(v) for v in o.get("xyz").split()])
        origin[joint.find("child").get("link")] = (joint.find("parent").get("link"), xyz, quat)
    poses: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def pose(link: str):
        if link not in poses:
            if link not in origin:
                poses[link] = (np.zeros(3), np.array([1.0, 0, 0, 0]))
            else:
                parent, xyz, quat = origin[link]
                p, q = pose(parent)
                moved, out = np.empty(3), np.empty(4)
                mujoco.mju_rotVecQuat(moved, xyz, q)
                mujoco.mju_mulQuat(out, q, quat)
                poses[link] = (p + moved, out)
        return poses[link]

    for link in root.findall("link"):
        pose(link.get("name"))
    return poses


@pytest.mark.parametrize("model", ["arm", "quadruped", "humanoid", "ur5e"])
def test_generated_urdf_is_one_tree_of_the_frames_with_every_joint(model, ur5e, mesh_cache):
    spec = batchsim.load(_model(model, ur5e))
    m = spec.mjmodel
    urdf = generate_urdf(spec)
    root = _check_urdf(urdf.text, m)
    tree = frame_tree(spec)
    links = {link.get("name") for link in root.findall("link")}
    assert set(tree.names) <= links | set() and (tree.root == "odom") == (tree.root not in links)
    joints = {j.get("name"): j for j in root.findall("joint")}
    for j in range(m.njnt):
        kind = int(m.jnt_type[j])
        if kind in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            el = joints[m.joint(j).name]
            expected = {mujoco.mjtJoint.mjJNT_SLIDE: "prismatic"}.get(
                kind, "revolute" if m.jnt_limited[j] else "continuous"
            )
            assert el.get("type") == expected
            np.testing.assert_allclose([float(v) for v in el.find("axis").get("xyz").split()], m.jnt_axis[j])
            if m.jnt_limited[j]:
                limit = el.find("limit")
                np.testing.assert_allclose(
                    [float(limit.get("lower")), float(limit.get("upper"))], m.jnt_range[j]
                )
    # with every joint at zero (qpos0), each body's link sits where MuJoCo puts the body
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    poses = _urdf_poses(root)
    base = 0 if tree.root == "world" else m.body(spec.floating_base.body).id
    for name, body in zip(tree.names, tree.body, strict=True):
        if name not in poses:
            continue
        p, q = poses[name]
        inverse = np.empty(4)
        mujoco.mju_negQuat(inverse, d.xquat[base])
        rel_p, rel_q = np.empty(3), np.empty(4)
        mujoco.mju_rotVecQuat(rel_p, d.xpos[body] - d.xpos[base], inverse)
        mujoco.mju_mulQuat(rel_q, inverse, d.xquat[body])
        np.testing.assert_allclose(p, rel_p, atol=1e-9, err_msg=name)
        assert abs(abs(np.dot(q, rel_q)) - 1.0) < 1e-9, name
    # meshes: binary STL files in the cache, referenced by absolute file:// URIs
    uris = [g.get("filename") for g in root.iter("mesh")]
    if model == "ur5e":
        assert uris and len(urdf.meshes) >= m.nmesh // 2
    for uri in uris:
        assert uri.startswith("file:///")
        path = Path(uri[len("file://") :])
        assert path.is_file() and mesh_cache in path.parents
        ntri = int(np.frombuffer(path.read_bytes()[80:84], np.uint32)[0])
        assert path.stat().st_size == 84 + 50 * ntri and ntri > 0


def test_rpy_is_urdfs_fixed_axis_convention():
    quat = np.array([0.9, 0.1, -0.3, 0.2])
    quat /= np.linalg.norm(quat)
    roll, pitch, yaw = rpy(quat)
    rz, ry, rx, out = np.empty(4), np.empty(4), np.empty(4), np.empty(4)
    mujoco.mju_axisAngle2Quat(rz, [0, 0, 1], yaw)
    mujoco.mju_axisAngle2Quat(ry, [0, 1, 0], pitch)
    mujoco.mju_axisAngle2Quat(rx, [1, 0, 0], roll)
    mujoco.mju_mulQuat(out, rz, ry)
    mujoco.mju_mulQuat(out, out, rx)
    assert abs(abs(np.dot(out, quat)) - 1) < 1e-12


def test_ball_joints_are_fixed_and_named_in_warnings(mesh_cache):
    m = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body name='a'><joint name='b' type='ball'/><geom type='ellipsoid' size='.1 .2 .3'/>"
        "</body></worldbody></mujoco>"
    )
    urdf = generate_urdf(m)
    root = _check_urdf(urdf.text, m)
    assert root.find("joint[@name='b']").get("type") == "fixed"
    assert any("ball joint 'b'" in w for w in urdf.warnings)
    assert [Path(p).name for p in urdf.meshes] == ["unit_sphere.stl"]  # the ellipsoid, scaled


def test_robot_description_is_the_users_urdf_else_the_generated_one(tmp_path, mesh_cache):
    spec = batchsim.load("arm")
    mine = tmp_path / "arm.urdf"
    mine.write_text('<robot name="mine"><link name="base"/></robot>')
    assert robot_description(spec, str(mine)) == mine.read_text()
    block = tmp_path / "block.xml"
    block.write_text('<ros2_control name="x" type="system"><hardware/></ros2_control>')
    assert 'robot name="arm"' in robot_description(spec, str(block))
    assert 'robot name="arm"' in robot_description(spec)


# ---------------------------------------------------------------- the device backends and fleets


def _skip_unless(backend: str) -> None:
    if (
        importlib.util.find_spec(BACKENDS[backend]) is None
        and os.environ.get("BATCHSIM_FORCE_BACKENDS") != "1"
    ):
        pytest.skip(f"backend {backend} needs {BACKENDS[backend]}, which is not installed")


@pytest.mark.parametrize("backend", ["mjx", "warp"])
def test_device_backends_body_poses_follow_cpu(backend):
    """float32 engines: the same poses as cpu's to float32 round-off, after reset and steps."""
    _skip_unless(backend)
    sims = [batchsim.make("arm", 2, b) for b in ("cpu", backend)]
    for sim in sims:
        sim.configure()
        sim.activate()
    first = [sim.body_poses() for sim in sims]  # the reset state's
    np.testing.assert_allclose(first[1][0], first[0][0], atol=1e-6)
    np.testing.assert_allclose(first[1][1], first[0][1], atol=1e-6)
    for period in range(3):
        for sim in sims:
            sim.command[:] = [[0.3 * period, -0.2, 0.1, 0.0, 0.2, -0.1], [0.1, 0.2, -0.3, 0.1, 0.0, 0.3]]
            sim.write()
            sim.step(10)
        (cpu_pos, cpu_quat), (pos, quat) = (sim.body_poses([1, 0]) for sim in sims)
        assert pos.dtype == np.float64 and pos.shape == cpu_pos.shape
        np.testing.assert_allclose(pos, cpu_pos, atol=1e-5)
        np.testing.assert_allclose(quat, cpu_quat, atol=1e-5)
    for sim in sims:
        sim.shutdown()


@pytest.mark.parametrize(
    "backend, options",
    [("cpu", {}), ("mjx", {}), ("warp", {}), ("warp", {"devices": ["cpu", "cpu"]})],
    ids=["cpu", "mjx", "warp", "warp-2dev"],
)
def test_body_poses_into_copies_what_body_poses_gives(backend, options):
    """tf's per-period copy (body_poses_into: the engine's rows straight into the channel, where
    it keeps them) gives the listed bodies of every world exactly as body_poses() does, from the
    first call on, consecutive bodies or not."""
    _skip_unless(backend)
    sim = batchsim.make("arm", 3, backend, **options)
    sim.configure()
    sim.activate()
    try:
        for period in range(3):
            for bodies in ([1, 2, 3], [4, 0, 2], list(range(sim.model.nbody))):
                out = np.full((3, len(bodies), 7), np.nan)
                sim.body_poses_into(out[..., :3], out[..., 3:], bodies)
                xpos, xquat = sim.body_poses()
                np.testing.assert_array_equal(out[..., :3], xpos[:, bodies])
                np.testing.assert_array_equal(out[..., 3:], xquat[:, bodies])
            sim.command[1] = 0.3 * (period + 1)
            sim.write()
            sim.step(10)
            sim.read()
        assert not np.allclose(xpos[1], xpos[0])  # world 1 moved: the copies follow the engine
    finally:
        sim.shutdown()


@pytest.mark.parametrize("processes", [False, True], ids=["threads", "processes"])
def test_a_fleet_over_two_devices_gives_the_poses_of_one_system(processes):
    _skip_unless("warp")
    fleets = [
        batchsim.make("arm", 3, "warp", devices=["cpu", "cpu"], processes=processes),
        batchsim.make("arm", 3, "warp"),
    ]
    try:
        for sim in fleets:
            sim.configure()
            sim.activate()
            sim.command[2] = [0.4, -0.3, 0.2, 0.1, -0.2, 0.3]
            sim.write()
            sim.step(10)
        (pos, quat), (one_pos, one_quat) = (sim.body_poses([2, 0, 1]) for sim in fleets)
        np.testing.assert_array_equal(pos, one_pos)
        np.testing.assert_array_equal(quat, one_quat)
        assert not np.allclose(pos[0], pos[1])  # world 2 moved, world 0 did not
    finally:
        for sim in fleets:
            sim.shutdown()


def test_every_link_of_the_generated_urdf_has_a_tf_frame():
    """RViz draws a link only where tf has its frame: the links of multi-joint bodies'
    chains are fixed children of their body (Urdf.extra_frames), at the joint's anchor."""
    import xml.etree.ElementTree as ET

    from batchsim.model.frames import frame_tree
    from batchsim.model.urdf import generate_urdf

    spec = batchsim.load("humanoid")
    urdf = generate_urdf(spec)
    tree = frame_tree(spec)
    links = {link.get("name") for link in ET.fromstring(urdf.text).iter("link")}
    extra = {link: (body, pos, quat) for body, link, pos, quat in urdf.extra_frames}
    assert extra and set(tree.names) <= links <= set(tree.names) | {tree.root} | set(extra)
    m = spec.mjmodel
    body, pos, quat = extra["waist_lower__abdomen_y"]
    assert body == "waist_lower"
    assert pos == pytest.approx(m.jnt_pos[m.joint("abdomen_y").id], abs=1e-12)
    assert quat == pytest.approx([1, 0, 0, 0], abs=1e-12)


def test_a_urdfs_links_fixed_to_known_frames_are_placed_as_its_joints_place_them():
    """A user's URDF whose links hang from the MJCF's frames by fixed joints is published, and tf
    places those links (ros_bridge/tf_plan.py); one behind a moving joint is not placed."""
    from batchsim.model.urdf import fixed_links, quat_of_rpy

    urdf = ET.fromstring(
        '<robot name="r"><link name="base"/><link name="camera_link"/><link name="optical"/><link name="wheel"/>'
        '<joint name="c" type="fixed"><parent link="base"/><child link="camera_link"/>'
        '<origin xyz="0.1 0 0.2" rpy="0 0.5 0"/></joint>'
        '<joint name="o" type="fixed"><parent link="camera_link"/><child link="optical"/>'
        '<origin rpy="-1.5707963 0 -1.5707963"/></joint>'
        '<joint name="w" type="continuous"><parent link="base"/><child link="wheel"/></joint></robot>'
    )
    placed = {link: (parent, pos, quat) for parent, link, pos, quat in fixed_links(urdf, {"base"})}
    assert set(placed) == {"camera_link", "optical"}  # the wheel moves: the MJCF's body, or nothing
    parent, pos, quat = placed["camera_link"]
    assert parent == "base" and np.allclose(pos, [0.1, 0, 0.2]) and np.allclose(rpy(quat), [0, 0.5, 0])
    assert placed["optical"][0] == "camera_link" and np.allclose(placed["optical"][2], [0.5, -0.5, 0.5, -0.5], atol=1e-7)
    assert np.allclose(rpy(quat_of_rpy(0.3, -0.7, 1.1)), [0.3, -0.7, 1.1])
