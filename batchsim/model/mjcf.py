"""Loading an MJCF: shipped models by name, files, strings; the `mujoco.ros2` extension block.

XML blocks that MuJoCo itself does not know are read and removed before compiling:
`<extension><plugin plugin="mujoco.ros2">` (its config keys are kept in `RobotSpec.ros`),
every `<ros2_control>` (handed to `batchsim.model.ros2_control`), in the file itself or in
a file it includes, and mujoco_ros2_control's lidar declarations, `<lidar>` and
`mujoco.plugin.lidar` (kept in `RobotSpec.sensor_declarations`, see `batchsim.model.lidars`).
MuJoCo then compiles the file with the stripped text standing in for it, so meshes,
textures and includes resolve from the file's own folder whatever the working directory.
"""

from __future__ import annotations

import importlib.resources
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco

from batchsim.model.description import Description, from_elements, not_text, parse_xml, read_description
from batchsim.model.from_urdf import is_urdf, mjcf_from_urdf
from batchsim.model.interfaces import discover
from batchsim.model.lidars import DeclarationError, SensorDeclarations, lidar_elements_of, take_declarations
from batchsim.model.spec import ROS2_PLUGIN, ROS2_PLUGIN_KEYS, ModelError, RobotSpec, RosPluginConfig


def _models_root():
    """The shipped models: the `batchsim.models` package once installed, else the checkout's models/."""
    try:
        return importlib.resources.files("batchsim.models")
    except ModuleNotFoundError:  # a source checkout on PYTHONPATH, not installed
        return Path(__file__).resolve().parents[2] / "models"


def model_names() -> list[str]:
    """The robots shipped with batchsim, loadable by name."""
    root = _models_root()
    return sorted(p.name[:-4] for p in root.iterdir() if p.name.endswith(".xml"))


def model_path(name: str) -> Path:
    """The MJCF file of a shipped model, or of a path; ModelError if neither exists."""
    path = Path(name).expanduser()
    if path.suffix.lower() in (".xml", ".mjcf") or path.exists():
        if not path.is_file():
            raise ModelError(f"{name}: no such file")
        return path
    shipped = _models_root() / f"{name}.xml"
    if not shipped.is_file():
        raise ModelError(
            f"unknown model {name!r}: not a file and not one of the shipped models "
            f"({', '.join(model_names())})"
        )
    return Path(str(shipped))


def load(
    model: str | Path,
    *,
    ros2_control: str | Path | None = None,
    keyframe: str | int | None = None,
    mujoco_inputs: str | Path | None = None,
    scene: str | Path | None = None,
) -> RobotSpec:
    """Load a shipped model by name, an MJCF file, or a URDF/xacro file into a RobotSpec.

    Args:
      model: a name from `models/` ("arm", "car", "quadruped"), a path to an MJCF file, or a
        URDF or xacro file (optionally followed by xacro `key:=value` arguments), compiled as
        mujoco_ros2_control's generation tool does (batchsim.model.from_urdf); its own
        `<ros2_control>` blocks then configure the interfaces unless `ros2_control` is given.
      ros2_control: the robot description whose `<ros2_control>` blocks narrow the exposed
        interfaces: a URDF/xacro/XML file (a xacro file may be followed by `key:=value`
        arguments: "robot.urdf.xacro use_pid:=true"), or the XML text itself. The MJCF's own
        inline `<ros2_control>` blocks are used when this is None.
      keyframe: the keyframe worlds start in and reset to, by name or index. None: the
        ros2_control block's `initial_keyframe`, else `home` if the model has one, else qpos0.
      mujoco_inputs, scene: for a URDF: a file of `<mujoco_inputs>` and an MJCF scene file,
        as the generation tool's `--m` and `--scene` take them.

    Raises:
      ModelError: a missing file, malformed XML, a model MuJoCo rejects, an unknown
        keyframe; one line.
    """
    return _load(model, ros2_control=ros2_control, keyframe=keyframe, mujoco_inputs=mujoco_inputs, scene=scene)[0]


def load_with_mjspec(
    model: str | Path,
    *,
    ros2_control: str | Path | None = None,
    keyframe: str | int | None = None,
    mujoco_inputs: str | Path | None = None,
    scene: str | Path | None = None,
) -> tuple[RobotSpec, mujoco.MjSpec]:
    """`load`, and the MjSpec the model compiled from (the extension and ros2_control blocks
    removed, assets resolved from the file's folder): what a fleet world attaches a robot from
    (batchsim.fleet). The MjSpec is the caller's own."""
    spec, mjspec = _load(
        model, ros2_control=ros2_control, keyframe=keyframe, mujoco_inputs=mujoco_inputs, scene=scene, keep=True
    )
    assert mjspec is not None
    return spec, mjspec


def _load(
    model: str | Path,
    *,
    ros2_control: str | Path | None,
    keyframe: str | int | None,
    mujoco_inputs: str | Path | None,
    scene: str | Path | None,
    keep: bool = False,
) -> tuple[RobotSpec, mujoco.MjSpec | None]:
    if is_urdf(model):
        generated = mjcf_from_urdf(model, inputs=mujoco_inputs, scene=scene)
        spec, mjspec = _load_string(
            generated.mjcf, name=generated.where, ros2_control=str(model) if ros2_control is None else ros2_control,
            keyframe=keyframe, generated=True, keep=keep,
        )  # fmt: skip
        spec.warnings += generated.warnings
        spec.path = Path(generated.where)  # the URDF it was made from (spec.xml holds the MJCF)
        return spec, mjspec
    if mujoco_inputs is not None or scene is not None:
        raise ModelError(f"{model}: mujoco inputs and a scene are for a URDF model, not an MJCF")
    path = model_path(str(model))
    try:
        text = path.read_text()
    except OSError as e:
        raise ModelError(f"{path}: {e.strerror}") from None
    except UnicodeDecodeError as e:
        raise ModelError(f"{path}: {not_text(e)}") from None
    return _load_string(text, path=path, ros2_control=ros2_control, keyframe=keyframe, keep=keep)


def load_string(
    text: str,
    *,
    path: Path | None = None,
    ros2_control: str | Path | None = None,
    keyframe: str | int | None = None,
    name: str | None = None,
    generated: bool = False,
) -> RobotSpec:
    """Load an MJCF given as text; `path`, if given, names it and anchors relative files
    (meshes, includes) as if MuJoCo had loaded the file itself; else `name` names it.
    `generated`: made from the URDF `ros2_control` names, whose `<lidar>`s it already holds."""
    return _load_string(
        text, path=path, ros2_control=ros2_control, keyframe=keyframe, name=name, generated=generated
    )[0]


def _load_string(
    text: str,
    *,
    path: Path | None = None,
    ros2_control: str | Path | None = None,
    keyframe: str | int | None = None,
    name: str | None = None,
    generated: bool = False,
    keep: bool = False,
) -> tuple[RobotSpec, mujoco.MjSpec | None]:
    """load_string, and with `keep` a copy of the MjSpec compiled (the caller's own), else None."""
    where = str(path) if path else (name or "<string>")
    root = parse_xml(text, where)
    if root.tag == "robot":
        raise ModelError(f"{where}: a URDF: give it as a .urdf or .xacro file, which batchsim compiles to MJCF")
    if root.tag != "mujoco":
        raise ModelError(f"{where}: not an MJCF file (root element <{root.tag}>, expected <mujoco>)")

    ros = _take_ros_plugin(root, where)
    try:  # lidars MuJoCo cannot compile (batchsim casts their rays itself)
        declarations = take_declarations(root, where)
    except DeclarationError as e:
        raise ModelError(str(e)) from None
    blocks = _take_all(root, "ros2_control")
    # included files carrying the blocks too are handed to MuJoCo stripped, under their own names
    overrides: dict[str, bytes] = {}
    if path is not None:
        for file, included in _includes(root, path.parent, where, (path.resolve(),)):
            inc_ros = _take_ros_plugin(included, file)
            inc_blocks = _take_all(included, "ros2_control")
            if inc_ros is not None or inc_blocks:
                overrides[file] = ET.tostring(included, encoding="unicode").encode()
                ros = ros or inc_ros
                blocks += inc_blocks
    stripped = ros is not None or bool(blocks) or bool(overrides) or bool(declarations)
    xml = ET.tostring(root, encoding="unicode") if stripped else text

    try:
        if path is None:
            mjspec = mujoco.MjSpec.from_string(xml)
        elif stripped:
            # the stripped text stands in for the file itself, so that MuJoCo resolves meshdir,
            # includes and assets from the file's folder exactly as from_xml_path does
            main = {path.name: xml.encode()}
            mjspec = mujoco.MjSpec.from_file(str(path), include={**overrides, **main})
        else:
            mjspec = mujoco.MjSpec.from_file(str(path))
        kept = mjspec.copy() if keep else None  # compile() binds the spec to its model: a fleet attaches a copy
        mjmodel = mjspec.compile()
    except ValueError as e:
        raise ModelError(f"{where}: {_one_line(str(e))}") from None

    description = None
    if ros2_control is not None:
        description = read_description(ros2_control)
    elif blocks:
        description = from_elements(blocks, where, path.parent if path else None)
    if description is not None:
        declarations = declarations.merged(_declared(description, lidars=not generated))
    name = root.get("model") or (path.stem if path else "model")
    key_ctrl = [len(k.ctrl) > 0 for k in mjspec.keys]
    try:
        spec = discover(name, path, mjmodel, xml, ros, description, keyframe=keyframe, key_ctrl_given=key_ctrl)
    except ModelError as e:
        raise ModelError(f"{where}: {e}") from None
    spec.sensor_declarations = declarations
    return spec, kept


def _declared(description: Description, lidars: bool = True) -> SensorDeclarations:
    """What a ros2_control file declares for the bridge's cameras and lidars: its `<lidar>`
    elements (of the expanded document), the params of its sensors without a mujoco_type,
    and the camera/lidar publish rates among its hardware params."""
    elements: tuple = ()
    if lidars and description.document is not None:
        try:
            elements = lidar_elements_of(description.document, description.where)
        except DeclarationError as e:
            raise ModelError(str(e)) from None
    params = tuple(
        (s.name, tuple(s.params.items())) for s in description.sensors if "mujoco_type" not in s.params and s.params
    )
    rates = tuple(
        (key, found[0]) for key in ("camera_publish_rate", "lidar_publish_rate") if (found := description.param(key))
    )
    return SensorDeclarations(elements, (), params, rates, description.where)


def _one_line(message: str) -> str:
    """MuJoCo's multi-line compile error as one line: 'XML Error: ... (Element 'x', line 5)'."""
    parts = [p.strip() for p in message.strip().splitlines() if p.strip()]
    if not parts:
        return "MuJoCo could not compile the model"
    head, rest = parts[0], parts[1:]
    return head + (f" ({'; '.join(rest)})" if rest else "")


def _take_all(root: ET.Element, tag: str) -> list[ET.Element]:
    """Remove and return every `tag` element anywhere under root, in document order."""
    found = []
    for parent in list(root.iter()):
        for child in list(parent):
            if child.tag == tag:
                parent.remove(child)
                found.append(child)
    return found


def _includes(root: ET.Element, base: Path, where: str, chain: tuple[Path, ...] = ()) -> list[tuple[str, ET.Element]]:
    """The files `<include>`d (recursively), as (the include's file attribute, parsed root).
    `chain`: the files whose includes led here; one that includes itself, directly or through
    others, is a ModelError naming the loop."""
    out = []
    for include in root.iter("include"):
        file = include.get("file")
        if not file:
            continue
        path = (base / file).resolve()
        if path in chain:
            loop = " -> ".join(p.name for p in (*chain, path))
            raise ModelError(f"{where}: its includes loop: {loop} (a file that includes itself)")
        try:
            text = path.read_text()
        except OSError:
            continue  # MuJoCo names the missing file when it compiles
        included = parse_xml(text, str(base / file))
        out.append((file, included))
        out += _includes(included, base, where, (*chain, path))
    return out


def _take_ros_plugin(root: ET.Element, where: str) -> RosPluginConfig | None:
    """Remove the `mujoco.ros2` extension plugin and return its config keys."""
    config = None
    for extension in root.findall("extension"):
        for plugin in extension.findall("plugin"):
            if plugin.get("plugin") != ROS2_PLUGIN:
                continue
            extension.remove(plugin)
            instance = plugin.find("instance")
            keys: dict[str, str] = {}
            if instance is not None:
                for c in instance.findall("config"):
                    keys[c.get("key", "")] = c.get("value", "")
            unknown = sorted(set(keys) - set(ROS2_PLUGIN_KEYS))
            if unknown:
                raise ModelError(
                    f"{where}: unknown {ROS2_PLUGIN} config key {unknown[0]!r} "
                    f"(known: {', '.join(ROS2_PLUGIN_KEYS)})"
                )
            try:
                depth = int(keys.get("topic_queue_size", 10))
            except ValueError:
                raise ModelError(
                    f"{where}: {ROS2_PLUGIN} topic_queue_size must be an integer, "
                    f"got {keys['topic_queue_size']!r}"
                ) from None
            reliability = keys.get("topic_reliability", "reliable").lower()
            if reliability not in ("reliable", "best_effort"):
                raise ModelError(
                    f"{where}: {ROS2_PLUGIN} topic_reliability must be reliable or "
                    f"best_effort, got {reliability!r}"
                )
            config = RosPluginConfig(
                instance=instance.get("name", "") if instance is not None else "",
                ros_namespace=keys.get("ros_namespace", ""),
                topic_queue_size=depth,
                topic_reliability=reliability,
            )
        if not list(extension):
            root.remove(extension)
    return config
