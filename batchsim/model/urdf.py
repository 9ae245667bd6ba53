"""robot_description from the MJCF: a URDF whose links are the tf frames of batchsim.model.frames.

    text = robot_description(spec)                       # the generated URDF
    text = robot_description(spec, "robot.urdf.xacro")   # the user's own URDF, xacro expanded
    urdf = generate_urdf(spec)                           # .text, .warnings, .meshes

RViz's RobotModel display draws each link at its tf frame, so links are named as the frames
(body names, `body_<id>` for an unnamed body) and their visuals are placed in the body frame.
Joints carry the MJCF joint names:

- hinge -> `revolute` with its range (`continuous` when unlimited), slide -> `prismatic`;
  a URDF joint's zero is the body's pose at qpos0 (a joint with a `ref` reads qpos - ref).
- several joints in one body -> a chain through links of their own, `<body>__<joint>`, which
  have no visuals; tf publishes them as fixed children of the body (`Urdf.extra_frames`),
  posed as at the body's later joints' zero, so that RViz finds a transform for every link.
- a hinge whose anchor is off the body's origin -> the joint at the anchor, then a fixed joint
  `<body>__anchor` back to the body's origin (URDF axes pass through the child's origin).
- no joint -> `fixed` (`<body>__fixed`); ball -> `fixed`, named in `warnings`.
- a free joint: the floating base's body is the root link, not attached (tf `odom -> base`
  places it), and the trees of other bodies on the world body are left out (named in
  `warnings`); in a fixed-base model the root link is `world` (the world body's geoms are
  its visuals) and a free body hangs from it by a `floating` joint.

Visuals are the geoms MuJoCo's viewer shows by default (groups 0-2, not fully transparent):
box, sphere and cylinder as themselves; a capsule as a cylinder and two spheres; an ellipsoid
as a scaled unit-sphere mesh; a mesh as the compiled mesh, written as binary STL to
`${XDG_CACHE_HOME:-~/.cache}/batchsim/meshes/<model hash>/<mesh>.stl` and referenced by a
`file://` URI; planes, height fields and SDFs are skipped. Each visual's material is its
geom's rgba (its material's where the geom keeps the default rgba). No `<inertial>`.
Joint limits carry MuJoCo's actuator force range as effort where the joint has one, else 0;
velocity is 0 (MuJoCo has no velocity limits).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import math
import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np

from batchsim.model.description import parse_xml, read_source
from batchsim.model.frames import body_frame_names, frame_tree
from batchsim.model.interfaces import floating_base
from batchsim.model.spec import RobotSpec

log = logging.getLogger("batchsim.urdf")

_T = mujoco.mjtJoint
_G = mujoco.mjtGeom
VISIBLE_GROUPS = (0, 1, 2)  # what MuJoCo's viewer shows by default
_DEFAULT_RGBA = np.array([0.5, 0.5, 0.5, 1.0], np.float32)
_UNLIMITED_SLIDE = 1e9  # m: a URDF prismatic joint must have limits


@dataclasses.dataclass
class Urdf:
    """A generated robot description.

    Attributes:
      text: the URDF XML.
      warnings: one line per thing the URDF cannot say as the MJCF does (ball joints, left-out trees).
      meshes: the STL files it references (written, or found written, in the cache).
      extra_frames: the links that are no body (`<body>__<joint>`, `<body>__anchor` chains),
        each as (its body's frame, the link, position (3,), quaternion w x y z (4,)): its
        pose in the body's frame with the body's later joints at zero. tf publishes them
        as fixed, so that RViz finds a transform for every link (they carry no visuals).
    """

    text: str
    warnings: list[str]
    meshes: list[Path]
    extra_frames: list[tuple[str, str, np.ndarray, np.ndarray]] = dataclasses.field(default_factory=list)


def robot_description(spec: RobotSpec, source: str | Path | None = None) -> str:
    """What the `robot_description` topic carries: the user's own URDF where `source` (the
    `--ros2-control` description: a file, optionally xacro with `key:=value` arguments) is a
    URDF (root `<robot>`), expanded; else the URDF generated from the model."""
    if source is not None:
        text, where, _ = read_source(source)
        if parse_xml(text, where).tag == "robot":
            return text
    return urdf_from_model(spec)


def urdf_from_model(model: RobotSpec | mujoco.MjModel, name: str | None = None) -> str:
    """The URDF generated from a model (see the module's docstring); warnings are logged."""
    urdf = generate_urdf(model, name)
    for line in urdf.warnings:
        log.warning("batchsim: robot_description: %s", line)
    return urdf.text


def generate_urdf(
    model: RobotSpec | mujoco.MjModel, name: str | None = None, *, cache_dir: Path | None = None
) -> Urdf:
    """The URDF of a RobotSpec or MjModel, named `name` (default: the spec's name, or "robot")."""
    m = model.mjmodel if isinstance(model, RobotSpec) else model
    if name is None:
        name = model.name if isinstance(model, RobotSpec) else "robot"
    tree = frame_tree(model)
    names = body_frame_names(m)
    meshes = _MeshCache(m, cache_dir)
    out = Urdf("", [], [])
    robot = ET.Element("robot", name=name)
    floating = tree.root == "odom"
    if floating:
        base = model.floating_base if isinstance(model, RobotSpec) else floating_base(m)
        base_body = int(m.jnt_bodyid[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, base.joint)])
        for b in range(1, m.nbody):
            if m.body_parentid[b] == 0 and b != base_body:
                out.warnings.append(
                    f"body {names[b]!r} is not part of the robot's tree: left out of the URDF"
                )
        included = {b for b in range(1, m.nbody) if int(m.body_rootid[b]) == base_body}
    else:
        included = set(range(1, m.nbody))
        _link(robot, tree.root, 0, m, meshes, out)
    joint_names = {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(m.njnt)}
    for b in range(1, m.nbody):
        if b not in included:
            continue
        _link(robot, names[b], b, m, meshes, out)
        if floating and b == base_body:
            continue  # the root link: tf odom -> base places it
        parent = tree.root if m.body_parentid[b] == 0 else names[m.body_parentid[b]]
        _joints(robot, m, b, names[b], parent, joint_names, out)
    out.meshes = meshes.written
    ET.indent(robot)
    out.text = '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"
    return out


def _joints(
    robot: ET.Element, m: mujoco.MjModel, b: int, link: str, parent: str, taken: set[str], out: Urdf
) -> None:
    """The URDF joints from `parent` to body `b`'s link `link`: one per MJCF joint, chained
    through links of their own (see the module's docstring)."""
    pos, quat = m.body_pos[b].copy(), m.body_quat[b].copy()  # the next joint's origin, in its parent
    joints = range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b])
    previous = parent
    chain: list[tuple[str, np.ndarray, np.ndarray]] = []  # (child link, its joint's origin pos, quat)
    for k, j in enumerate(joints):
        jname = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint_{j}"
        kind = int(m.jnt_type[j])
        anchor = m.jnt_pos[j].copy() if kind in (_T.mjJNT_HINGE, _T.mjJNT_BALL) else np.zeros(3)
        pos = pos + _rotate(quat, anchor)
        last = k == len(joints) - 1
        child = link if last and not anchor.any() else f"{link}__{jname}"
        if child != link:
            ET.SubElement(robot, "link", name=child)
        el = ET.SubElement(robot, "joint", name=jname, type=_joint_type(m, j, jname, out))
        _origin(el, pos, quat)
        ET.SubElement(el, "parent", link=previous)
        ET.SubElement(el, "child", link=child)
        chain.append((child, pos.copy(), quat.copy()))
        if kind in (_T.mjJNT_HINGE, _T.mjJNT_SLIDE):
            ET.SubElement(el, "axis", xyz=_floats(m.jnt_axis[j]))
            _limit(el, m, j)
        previous, pos, quat = child, -anchor, np.array([1.0, 0.0, 0.0, 0.0])
    if previous != link:
        el = ET.SubElement(
            robot,
            "joint",
            name=_unique(f"{link}__{'anchor' if len(joints) else 'fixed'}", taken),
            type="fixed",
        )
        _origin(el, pos, quat)
        ET.SubElement(el, "parent", link=previous)
        ET.SubElement(el, "child", link=link)
        chain.append((link, pos.copy(), quat.copy()))
    # each link of the chain but the body's own, posed in the body's frame (later joints at zero)
    to_body_pos, to_body_quat = np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])  # link -> body
    for k in range(len(chain) - 1, 0, -1):
        _, p, q = chain[k]  # the origin of chain[k] in chain[k - 1]'s frame
        pos_out, quat_out = np.zeros(3), np.zeros(4)
        mujoco.mju_mulPose(pos_out, quat_out, p, q, to_body_pos, to_body_quat)
        to_body_pos, to_body_quat = pos_out, quat_out
        inv_pos, inv_quat = np.zeros(3), np.zeros(4)
        mujoco.mju_negPose(inv_pos, inv_quat, to_body_pos, to_body_quat)
        out.extra_frames.append((link, chain[k - 1][0], inv_pos, inv_quat))


def _joint_type(m: mujoco.MjModel, j: int, name: str, out: Urdf) -> str:
    kind = int(m.jnt_type[j])
    if kind == _T.mjJNT_HINGE:
        return "revolute" if m.jnt_limited[j] else "continuous"
    if kind == _T.mjJNT_SLIDE:
        return "prismatic"
    if kind == _T.mjJNT_FREE:
        return "floating"
    out.warnings.append(f"ball joint {name!r}: a fixed joint in the URDF (URDF has no ball joint)")
    return "fixed"


def _limit(el: ET.Element, m: mujoco.MjModel, j: int) -> None:
    effort = float(np.abs(m.jnt_actfrcrange[j]).max()) if m.jnt_actfrclimited[j] else 0.0
    if m.jnt_limited[j]:
        lower, upper = m.jnt_range[j]
    elif int(m.jnt_type[j]) == _T.mjJNT_SLIDE:
        lower, upper = -_UNLIMITED_SLIDE, _UNLIMITED_SLIDE
    else:  # continuous
        ET.SubElement(el, "limit", effort=_floats([effort]), velocity="0")
        return
    ET.SubElement(
        el, "limit", lower=_floats([lower]), upper=_floats([upper]), effort=_floats([effort]), velocity="0"
    )


def _link(robot: ET.Element, name: str, b: int, m: mujoco.MjModel, meshes: _MeshCache, out: Urdf) -> None:
    """Link `name` with body `b`'s visible geoms as visuals."""
    link = ET.SubElement(robot, "link", name=name)
    for g in range(m.body_geomadr[b], m.body_geomadr[b] + m.body_geomnum[b]):
        rgba = m.geom_rgba[g]
        if m.geom_matid[g] >= 0 and np.array_equal(rgba, _DEFAULT_RGBA):
            rgba = m.mat_rgba[m.geom_matid[g]]
        if int(m.geom_group[g]) not in VISIBLE_GROUPS or rgba[3] == 0:
            continue
        kind, size = int(m.geom_type[g]), m.geom_size[g]
        pos, quat = m.geom_pos[g], m.geom_quat[g]
        shapes: list[tuple[float, str, dict[str, str]]] = []  # (offset along the geom's z, tag, attributes)
        if kind == _G.mjGEOM_BOX:
            shapes.append((0.0, "box", {"size": _floats(2 * size)}))
        elif kind == _G.mjGEOM_SPHERE:
            shapes.append((0.0, "sphere", {"radius": _floats(size[:1])}))
        elif kind == _G.mjGEOM_CYLINDER:
            shapes.append((0.0, "cylinder", {"radius": _floats(size[:1]), "length": _floats([2 * size[1]])}))
        elif kind == _G.mjGEOM_CAPSULE:
            shapes.append((0.0, "cylinder", {"radius": _floats(size[:1]), "length": _floats([2 * size[1]])}))
            shapes += [(s * size[1], "sphere", {"radius": _floats(size[:1])}) for s in (-1.0, 1.0)]
        elif kind == _G.mjGEOM_ELLIPSOID:
            shapes.append((0.0, "mesh", {"filename": meshes.unit_sphere(), "scale": _floats(size)}))
        elif kind == _G.mjGEOM_MESH:
            shapes.append((0.0, "mesh", {"filename": meshes.mesh(int(m.geom_dataid[g]))}))
        else:
            continue  # plane, height field, SDF: nothing RViz's RobotModel can draw
        for offset, tag, attributes in shapes:
            visual = ET.SubElement(link, "visual")
            _origin(visual, pos + _rotate(quat, np.array([0.0, 0.0, offset])), quat)
            ET.SubElement(ET.SubElement(visual, "geometry"), tag, attributes)
            material = ET.SubElement(visual, "material", name=f"{name}_geom{g}")
            ET.SubElement(material, "color", rgba=_floats(rgba, 6))


def _origin(el: ET.Element, pos: np.ndarray, quat: np.ndarray) -> None:
    ET.SubElement(el, "origin", xyz=_floats(pos), rpy=_floats(rpy(quat)))


def rpy(quat: np.ndarray) -> np.ndarray:
    """URDF's roll, pitch, yaw (fixed axes x, y, z: R = Rz(yaw) Ry(pitch) Rx(roll)) of a
    quaternion (w, x, y, z)."""
    r = np.empty(9)
    mujoco.mju_quat2Mat(r, np.asarray(quat, np.float64) / np.linalg.norm(quat))
    r = r.reshape(3, 3)
    pitch = math.asin(max(-1.0, min(1.0, -r[2, 0])))
    if abs(r[2, 0]) < 1.0 - 1e-12:
        return np.array([math.atan2(r[2, 1], r[2, 2]), pitch, math.atan2(r[1, 0], r[0, 0])])
    return np.array([math.atan2(-r[1, 2], r[1, 1]), pitch, 0.0])  # gimbal lock: yaw folded into roll


def quat_of_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """The quaternion (w, x, y, z) of URDF's roll, pitch, yaw (fixed axes x, y, z); `rpy`'s inverse."""
    out = np.empty(4)
    mujoco.mju_euler2Quat(out, np.array([roll, pitch, yaw], np.float64), "XYZ")
    return out


def fixed_links(urdf: ET.Element, known: set[str]) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
    """A URDF's links that are no frame in `known` but hang from one through fixed joints, as
    (parent frame, link, position (3,), quaternion w x y z (4,)) from the joints' origins."""
    out: list[tuple[str, str, np.ndarray, np.ndarray]] = []
    have = set(known)
    fixed = [j for j in urdf.findall("joint") if j.get("type") == "fixed"]
    grew = True
    while grew:
        grew = False
        for joint in fixed:
            parent, child = joint.find("parent"), joint.find("child")
            if parent is None or child is None:
                continue
            p, c = parent.get("link"), child.get("link")
            if p in have and c not in have:
                origin = joint.find("origin")
                xyz = [float(v) for v in (origin.get("xyz", "0 0 0") if origin is not None else "0 0 0").split()]
                rpy_ = [float(v) for v in (origin.get("rpy", "0 0 0") if origin is not None else "0 0 0").split()]
                out.append((p, c, np.array(xyz), quat_of_rpy(*rpy_)))
                have.add(c)
                grew = True
    return out


def _rotate(quat: np.ndarray, v: np.ndarray) -> np.ndarray:
    out = np.empty(3)
    mujoco.mju_rotVecQuat(out, np.asarray(v, np.float64), np.asarray(quat, np.float64))
    return out


def _floats(values, digits: int = 12) -> str:
    return " ".join(f"{float(v) + 0.0:.{digits}g}" for v in values)  # + 0.0: no "-0"


def _unique(name: str, taken: set[str]) -> str:
    while name in taken:
        name += "_"
    taken.add(name)
    return name


class _MeshCache:
    """STL files of a model's meshes, in a folder of the model's hash (written once)."""

    def __init__(self, m: mujoco.MjModel, cache_dir: Path | None):
        self.m = m
        self._root = cache_dir
        self._folder: Path | None = None
        self.written: list[Path] = []

    @property
    def folder(self) -> Path:
        if self._folder is None:
            root = self._root
            if root is None:
                root = (
                    Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "batchsim" / "meshes"
                )
            buffer = np.empty(mujoco.mj_sizeModel(self.m), np.uint8)
            mujoco.mj_saveModel(self.m, None, buffer)
            self._folder = Path(root) / hashlib.sha256(buffer.tobytes()).hexdigest()[:16]
            self._folder.mkdir(parents=True, exist_ok=True)
        return self._folder

    def mesh(self, i: int) -> str:
        m = self.m
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_MESH, i) or f"mesh_{i}"
        vert = m.mesh_vert[m.mesh_vertadr[i] : m.mesh_vertadr[i] + m.mesh_vertnum[i]]
        face = m.mesh_face[m.mesh_faceadr[i] : m.mesh_faceadr[i] + m.mesh_facenum[i]]
        return self._write(f"{re.sub(r'[^A-Za-z0-9_.-]', '_', name)}_{i}.stl", vert[face])

    def unit_sphere(self) -> str:
        return self._write("unit_sphere.stl", _unit_sphere())

    def _write(self, filename: str, triangles: np.ndarray) -> str:
        path = self.folder / filename
        if not path.exists():
            tmp = path.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_bytes(stl_bytes(triangles))
            os.replace(tmp, path)  # whole or not at all, should two processes write it at once
        if path not in self.written:
            self.written.append(path)
        return path.resolve().as_uri()


def stl_bytes(triangles: np.ndarray) -> bytes:
    """Binary STL of triangles `(ntri, 3, 3)` (vertices counter-clockwise seen from outside)."""
    tri = np.asarray(triangles, np.float32).reshape(-1, 3, 3)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.divide(normal, length, out=np.zeros_like(normal), where=length > 0)
    record = np.zeros(
        len(tri), dtype=[("normal", "<f4", 3), ("vertices", "<f4", (3, 3)), ("attribute", "<u2")]
    )
    record["normal"], record["vertices"] = normal, tri
    header = b"batchsim: a MuJoCo mesh, compiled".ljust(80, b" ")
    return header + np.uint32(len(tri)).tobytes() + record.tobytes()


def _unit_sphere(subdivisions: int = 2) -> np.ndarray:
    """A unit icosphere, (ntri, 3, 3)."""
    t = (1.0 + 5.0**0.5) / 2.0
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t),
         (0, -1, -t), (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]  # fmt: skip
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
         (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5),
         (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]  # fmt: skip
    tri = np.array(v, float)[np.array(f)]
    tri /= np.linalg.norm(tri, axis=-1, keepdims=True)
    for _ in range(subdivisions):
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
        tri = np.concatenate([np.stack(x, 1) for x in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
        tri /= np.linalg.norm(tri, axis=-1, keepdims=True)
    return tri
