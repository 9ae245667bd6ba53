"""A robot described only by a URDF (or xacro), compiled to a simulation the way
mujoco_ros2_control's generation tool (`make_mjcf_from_robot_description.py`) does it.

MuJoCo compiles the URDF itself: every link becomes a body, then the static ones (fixed
joints) are fused into their parents; each link keeps a site of its own name at its frame,
so sensors, cameras and tf find every link. The URDF's `<mujoco_inputs>` (and a separate
inputs file, and a scene file, as the tool's `--m` and `--scene` take them) add what URDF
cannot say:

    <mujoco_inputs>
      <raw_inputs>...</raw_inputs>          MJCF copied in as is: option, default, actuator,
                                            tendon, equality, sensor, ...
      <processed_inputs>
        <camera site="..." name=".." .../> a camera at a link's site, looking along its +z
                                            (REP 103 optical frame) as the tool places it
        <lidar ref_site=".." sensor_name=".." min_angle max_angle angle_increment/>
                                            a fan of rangefinder sites, replicated as the tool does
        <modify_element type="joint" name=".." attr="..."/>   attributes set on a named element
        <decompose_mesh .../>               not done (convex decomposition): warned
      </processed_inputs>
      <scene>...</scene>                    MJCF copied in: lights, floor, visual, ...
    </mujoco_inputs>

`package://pkg/...` mesh paths resolve like `$(find pkg)` (ament's index, else a folder
named `pkg` at or above the URDF). MuJoCo reads STL, OBJ and MSH meshes; a COLLADA (.dae)
mesh is refused naming the file (the tool converts them with obj2mjcf).
"""

from __future__ import annotations

import dataclasses
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np

from batchsim.model.description import parse_xml, read_source, resolve_package
from batchsim.model.spec import ModelError

URDF_SUFFIXES = (".urdf", ".xacro")
_DROPPED = ("ros2_control", "transmission", "gazebo", "mujoco_inputs", "mujoco")
_MESH_FORMATS = (".stl", ".obj", ".msh")
_X_PI = (0.0, 1.0, 0.0, 0.0)  # pi about x: a MuJoCo camera looks along -z, an optical frame along +z
_LIDAR_FRAME = (0.5, 0.5, 0.5, 0.5)  # pi/2 about x, then pi/2 about y: the tool's rangefinder frame


@dataclasses.dataclass
class Generated:
    """An MJCF generated from a URDF.

    Attributes:
      mjcf: the MJCF text (what `batchsim info --mjcf` prints and `/mujoco_robot_description` carries).
      where: the URDF file, for messages.
      warnings: what was read and not done.
    """

    mjcf: str
    where: str
    warnings: list[str]


def is_urdf(model: str | Path) -> bool:
    """Whether `model` names a URDF or xacro file (optionally followed by xacro `key:=value` args)."""
    first = str(model).split(" ", 1)[0].lower()
    return first.endswith(URDF_SUFFIXES) or first.endswith(".urdf.xml")


def mjcf_from_urdf(source: str | Path, *, inputs: str | Path | None = None, scene: str | Path | None = None) -> Generated:
    """Compile a URDF (file, optionally with xacro args) into MJCF text.

    Args:
      source: the URDF or xacro file ("robot.urdf.xacro use_pid:=true").
      inputs: a file holding `<mujoco_inputs>` (or its `raw_inputs`/`processed_inputs`), added
        to the URDF's own.
      scene: an MJCF file whose top-level elements are copied in (lights, floor, ...).

    Raises:
      ModelError: a missing file, a xacro error, a mesh MuJoCo cannot read, a site a camera
        or lidar names that no link makes, a URDF MuJoCo cannot compile; one line.
    """
    text, where, path = read_source(source, what="URDF")
    root = parse_xml(text, where)
    if root.tag != "robot":
        raise ModelError(f"{where}: not a URDF (root element <{root.tag}>, expected <robot>)")
    warnings: list[str] = []
    blocks = [el for el in root.findall("mujoco_inputs")]
    if inputs is not None:
        blocks.append(_inputs_file(inputs))
    for tag in _DROPPED:
        for el in root.findall(tag):
            root.remove(el)
    directory = path.parent if path is not None else Path.cwd()
    _resolve_meshes(root, directory, where)
    mujoco_ext = ET.SubElement(root, "mujoco")
    ET.SubElement(
        mujoco_ext, "compiler", fusestatic="false", discardvisual="false", balanceinertia="true", strippath="false",
        angle="radian",
    )  # fmt: skip
    try:
        spec = mujoco.MjSpec.from_string(ET.tostring(root, encoding="unicode"))
        names = {s.name for s in spec.sites}
        for body in spec.bodies:  # each link keeps its frame as a site of its name
            if body.name and body.name not in names:
                body.add_site(name=body.name)
        spec.compiler.fusestatic = True  # fixed links fused into their bodies: <frame>s holding their sites
        spec.compile()
        mjcf = parse_xml(spec.to_xml(), where)
    except ValueError as e:
        raise ModelError(f"{where}: MuJoCo cannot compile this URDF: {_one_line(str(e))}") from None
    for block in blocks:
        _apply_inputs(mjcf, block, where, warnings)
    if scene is not None:
        _copy_children(_read_root(scene, "scene"), mjcf)
    return Generated(ET.tostring(mjcf, encoding="unicode"), where, warnings)


# --- inputs ---
def _apply_inputs(mjcf: ET.Element, block: ET.Element, where: str, warnings: list[str]) -> None:
    raw = block.find("raw_inputs")
    processed = block.find("processed_inputs")
    scene = block.find("scene")
    if raw is None and processed is None and scene is None:  # an inputs file of bare sections
        raw = block
    if scene is not None:
        _copy_children(scene, mjcf)
    if raw is not None:
        _copy_children(raw, mjcf)
    if processed is None:
        return
    for el in processed:
        if el.tag == "camera":
            _add_camera(mjcf, dict(el.attrib), where)
        elif el.tag == "lidar":
            _add_lidar(mjcf, el, where)
        elif el.tag == "modify_element":
            _modify(mjcf, dict(el.attrib), where, warnings)
        elif el.tag == "decompose_mesh":
            warnings.append(f"{where}: <decompose_mesh mesh_name={el.get('mesh_name')!r}>: not done (no convex decomposition)")
        else:
            warnings.append(f"{where}: <processed_inputs> element <{el.tag}> is unknown to batchsim: ignored")


def _copy_children(source: ET.Element, mjcf: ET.Element) -> None:
    for child in source:
        mjcf.append(child)


def _site(mjcf: ET.Element, name: str, what: str, where: str) -> tuple[ET.Element, ET.Element]:
    """(the site named `name`, its parent element)."""
    for parent in mjcf.iter():
        for child in parent:
            if child.tag == "site" and child.get("name") == name:
                return child, parent
    raise ModelError(f"{where}: {what}: no link (site) named {name!r} in the URDF")


def _quat(el: ET.Element) -> np.ndarray:
    return np.array([float(v) for v in el.get("quat", "1 0 0 0").split()])


def _mul(a: np.ndarray | tuple, b: np.ndarray | tuple) -> np.ndarray:
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, np.asarray(a, float), np.asarray(b, float))
    return out


def _fmt(values: np.ndarray) -> str:
    return " ".join(f"{v:.12g}" for v in values)


def _add_camera(mjcf: ET.Element, attrs: dict, where: str) -> None:
    site_name = attrs.pop("site", "")
    site, parent = _site(mjcf, site_name, f"<camera name={attrs.get('name')!r}>", where)
    camera = ET.Element("camera", attrs)
    camera.set("pos", site.get("pos", "0 0 0"))
    camera.set("quat", _fmt(_mul(_quat(site), _X_PI)))
    parent.append(camera)


def _add_lidar(mjcf: ET.Element, el: ET.Element, where: str) -> None:
    site_name = el.get("ref_site", "")
    try:
        lo, hi, step = (float(el.get(k, "nan")) for k in ("min_angle", "max_angle", "angle_increment"))
    except ValueError:
        lo = hi = step = math.nan
    if not (math.isfinite(lo) and math.isfinite(hi) and step > 0):
        raise ModelError(f"{where}: <lidar ref_site={site_name!r}>: min_angle, max_angle and angle_increment > 0 are needed")
    site, parent = _site(mjcf, site_name, f"<lidar ref_site={site_name!r}>", where)
    euler = np.array([0.0, lo, 0.0])
    turn = np.zeros(4)
    mujoco.mju_euler2Quat(turn, euler, "xyz")
    body = ET.Element("body", name=f"{site_name}_lidar_body", pos=site.get("pos", "0 0 0"))
    body.set("quat", _fmt(_mul(_mul(_quat(site), _LIDAR_FRAME), turn)))
    replicate = ET.SubElement(
        body, "replicate", count=str(int((hi - lo) / step) + 1), sep="-", offset="0 0 0", euler=f"0 {step:.12g} 0"
    )
    ET.SubElement(replicate, "site", name=el.get("sensor_name", site_name), pos="0 0 0", quat="0 0 0 1")
    if parent.tag == "frame":  # bodies may not sit in a static link's frame element: its parent body takes it
        frame_pos = np.array([float(v) for v in parent.get("pos", "0 0 0").split()])
        frame_quat = _quat(parent)
        pos = np.zeros(3)
        mujoco.mju_rotVecQuat(pos, np.array([float(v) for v in body.get("pos").split()]), frame_quat)
        body.set("pos", _fmt(pos + frame_pos))
        body.set("quat", _fmt(_mul(frame_quat, _quat(body))))
        parent = _parent_of(mjcf, parent)
    parent.append(body)


def _parent_of(mjcf: ET.Element, element: ET.Element) -> ET.Element:
    for parent in mjcf.iter():
        if any(child is element for child in parent):
            return parent
    raise ModelError("internal: element without a parent")


def _modify(mjcf: ET.Element, attrs: dict, where: str, warnings: list[str]) -> None:
    kind, name = attrs.pop("type", None), attrs.pop("name", None)
    if kind is None or name is None:
        raise ModelError(f"{where}: <modify_element> needs `type` and `name`")
    worldbody = mjcf.find("worldbody")
    found = [el for el in (worldbody.iter(kind) if worldbody is not None else []) if el.get("name") == name]
    if not found:
        warnings.append(f"{where}: <modify_element type={kind!r} name={name!r}>: no such element: nothing modified")
    for el in found:
        for key, value in attrs.items():
            el.set(key, value)


def _inputs_file(source: str | Path) -> ET.Element:
    root = _read_root(source, "MuJoCo inputs")
    found = root if root.tag == "mujoco_inputs" else root.find("mujoco_inputs")
    return found if found is not None else root


def _read_root(source: str | Path, what: str) -> ET.Element:
    text, where, _ = read_source(source, what=what)
    return parse_xml(text, where)


def _resolve_meshes(root: ET.Element, directory: Path, where: str) -> None:
    for mesh in root.iter("mesh"):
        name = mesh.get("filename")
        if not name:
            continue
        if name.startswith("package://"):
            package, _, rest = name[len("package://") :].partition("/")
            file = Path(resolve_package(package, directory)) / rest
        elif name.startswith("file://"):
            file = Path(name[len("file://") :])
        else:
            file = directory / name
        if file.suffix.lower() not in _MESH_FORMATS:
            raise ModelError(
                f"{where}: mesh {name!r}: MuJoCo reads STL, OBJ and MSH meshes, not {file.suffix or 'this'} "
                "(convert it, e.g. with obj2mjcf as mujoco_ros2_control's tool does)"
            )
        if not file.is_file():
            raise ModelError(f"{where}: mesh {name!r}: no file {file}")
        mesh.set("filename", str(file.resolve()))


def _one_line(message: str) -> str:
    return "; ".join(p.strip() for p in message.strip().splitlines() if p.strip())
