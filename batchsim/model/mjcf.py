"""Loading an MJCF: shipped models by name, files, strings; the `mujoco.ros2` extension block.

XML blocks that MuJoCo itself does not know are read and removed before compiling:
`<extension><plugin plugin="mujoco.ros2">` (its config keys are kept in `RobotSpec.ros`),
`<ros2_control>` (handed to `batchsim.model.ros2_control`), and mujoco_ros2_control's lidar
declarations, `<lidar>` and `mujoco.plugin.lidar` (kept in `RobotSpec.sensor_declarations`,
see `batchsim.sensors.mjcf`). File references are then
made absolute, since the stripped XML is compiled from a string.
"""

from __future__ import annotations

import importlib.resources
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco

from batchsim.model.interfaces import discover
from batchsim.model.ros2_control import block_of, xml_error_reason
from batchsim.model.spec import ROS2_PLUGIN, ROS2_PLUGIN_KEYS, ModelError, RobotSpec, RosPluginConfig
from batchsim.sensors.mjcf import DeclarationError, lidar_elements_of, take_declarations


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


def load(model: str | Path, *, ros2_control: str | Path | None = None) -> RobotSpec:
    """Load a shipped model by name or an MJCF file by path into a RobotSpec.

    Args:
      model: a name from `models/` ("arm", "car", "quadruped") or a path to an MJCF file.
      ros2_control: a ros2_control block narrowing the exposed interfaces: a path to a
        URDF/XML file that contains one, or the XML text itself. An inline
        `<ros2_control>` in the MJCF is used when this is None.

    Raises:
      ModelError: a missing file, malformed XML, or a model MuJoCo rejects; one line.
    """
    path = model_path(str(model))
    try:
        text = path.read_text()
    except OSError as e:
        raise ModelError(f"{path}: {e.strerror}") from None
    return load_string(text, path=path, ros2_control=ros2_control)


def load_string(
    text: str, *, path: Path | None = None, ros2_control: str | Path | None = None
) -> RobotSpec:
    """Load an MJCF given as text; `path`, if given, names it and anchors relative assets."""
    where = str(path) if path else "<string>"
    try:
        root = ET.fromstring(text)
    except ET.ParseError as e:
        line, col = e.position
        raise ModelError(f"{where}:{line}:{col}: malformed XML: {xml_error_reason(e)}") from None
    if root.tag != "mujoco":
        raise ModelError(f"{where}: not an MJCF file (root element <{root.tag}>, expected <mujoco>)")

    ros = _take_ros_plugin(root, where)
    try:  # lidars MuJoCo cannot compile (batchsim casts their rays itself)
        declarations = take_declarations(root, where)
    except DeclarationError as e:
        raise ModelError(str(e)) from None
    inline_block = _take_element(root, "ros2_control")
    stripped = ros is not None or inline_block is not None or bool(declarations)
    if stripped and path is not None:
        _anchor_relative_files(root, path.parent)
    xml = ET.tostring(root, encoding="unicode") if stripped else text

    try:
        if stripped or path is None:
            mjmodel = mujoco.MjModel.from_xml_string(xml)
        else:
            mjmodel = mujoco.MjModel.from_xml_path(str(path))
    except ValueError as e:
        raise ModelError(f"{where}: {_one_line(str(e))}") from None

    block = inline_block
    if ros2_control is not None:
        block = block_of(ros2_control)
        try:
            extra = lidar_elements_of(ros2_control)
        except DeclarationError as e:
            raise ModelError(str(e)) from None
        declarations = declarations.merged(type(declarations)(lidar_elements=extra))
    name = root.get("model") or (path.stem if path else "model")
    spec = discover(name, path, mjmodel, xml, ros, block)
    spec.sensor_declarations = declarations
    return spec


def _one_line(message: str) -> str:
    """MuJoCo's multi-line compile error as one line: 'XML Error: ... (Element 'x', line 5)'."""
    parts = [p.strip() for p in message.strip().splitlines() if p.strip()]
    if not parts:
        return "MuJoCo could not compile the model"
    head, rest = parts[0], parts[1:]
    return head + (f" ({'; '.join(rest)})" if rest else "")


def _take_element(root: ET.Element, tag: str) -> ET.Element | None:
    """Remove and return the first `tag` element anywhere under root."""
    for parent in root.iter():
        for child in list(parent):
            if child.tag == tag:
                parent.remove(child)
                return child
    return None


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


def _anchor_relative_files(root: ET.Element, base: Path) -> None:
    """Make file references absolute, since the stripped XML is compiled from a string."""
    base = base.resolve()
    compiler = root.find("compiler")
    if compiler is None:
        compiler = ET.Element("compiler")
        root.insert(0, compiler)
    for key in ("meshdir", "texturedir", "assetdir"):
        value = compiler.get(key)
        if value is not None and not Path(value).is_absolute():
            compiler.set(key, str(base / value))
    if compiler.get("meshdir") is None and compiler.get("texturedir") is None:
        compiler.set("assetdir", compiler.get("assetdir", str(base)))
    for include in root.iter("include"):
        file = include.get("file")
        if file and not Path(file).is_absolute():
            include.set("file", str(base / file))
