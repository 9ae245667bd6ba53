"""Robot descriptions as ros2_control reads them: the `<ros2_control>` blocks of a URDF (xacro
expanded), of an XML file, or inline in an MJCF, as plain data.

    description = read_description("robot.urdf.xacro use_pid:=true")
    for hw in description.hardware:      # one per <ros2_control> block
        hw.params["initial_keyframe"], [j.name for j in hw.joints]

A file whose name ends in `.xacro`, or that declares the xacro namespace, is expanded with
the `xacro` package first, with the `key:=value` arguments that follow its path.
`$(find pkg)` resolves through ament's index (a sourced ROS), else to a folder named `pkg`
at or above the file's own folder (a checkout of the package's repository).
Anything in a block that batchsim does not understand is named in `warnings`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import re
import shlex
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterator
from pathlib import Path

from batchsim.model.spec import ModelError

XACRO_NS = "http://www.ros.org/wiki/xacro"

# <hardware> params and what batchsim does with them
HARDWARE_PARAMS = {
    "initial_keyframe": "the keyframe worlds start in",
    "pids_config_file": "PID gains for position/velocity interfaces on motors",
    "odom_free_joint_name": "the floating base",
    "force_mjcf_suffix": "", "torque_mjcf_suffix": "", "orientation_mjcf_suffix": "",
    "angular_velocity_mjcf_suffix": "", "linear_acceleration_mjcf_suffix": "", "position_mjcf_suffix": "",
}
# mujoco_ros2_control's params that have no meaning in batchsim (the model comes from --model,
# there is no viewer, rates are flags): accepted without a warning
HARDWARE_PARAMS_UNUSED = (
    "mujoco_model", "mujoco_model_topic", "headless", "sim_speed_factor", "camera_publish_rate",
    "lidar_publish_rate", "odom_topic", "disable_rendering",
)


@dataclasses.dataclass(frozen=True)
class InterfaceInfo:
    """One `<command_interface>` or `<state_interface>`: its name and `<param>`s."""

    name: str
    params: dict[str, str]


@dataclasses.dataclass(frozen=True)
class MimicInfo:
    """A mimic joint: position = multiplier * mimicked joint's + offset."""

    joint: str
    multiplier: float = 1.0
    offset: float = 0.0


@dataclasses.dataclass(frozen=True)
class ComponentInfo:
    """A `<joint>`, `<sensor>` or `<gpio>` of a block."""

    name: str
    params: dict[str, str]
    command_interfaces: tuple[InterfaceInfo, ...]
    state_interfaces: tuple[InterfaceInfo, ...]
    mimic: MimicInfo | None = None


@dataclasses.dataclass(frozen=True)
class TransmissionEnd:
    """A `<joint>` or `<actuator>` of a `<transmission>`: its `<mechanical_reduction>` and
    `<offset>` (1 and 0 when not given, as ros2_control's parser defaults them); the text of
    either when it is not a number, for the problem it makes."""

    name: str
    role: str
    mechanical_reduction: float = 1.0
    offset: float = 0.0
    bad: str = ""


@dataclasses.dataclass(frozen=True)
class TransmissionInfo:
    """A `<transmission>` of a block (hardware_interface::TransmissionInfo)."""

    name: str
    plugin: str
    joints: tuple[TransmissionEnd, ...]
    actuators: tuple[TransmissionEnd, ...]
    params: dict[str, str]


@dataclasses.dataclass(frozen=True)
class HardwareInfo:
    """One `<ros2_control>` block (hardware_interface::HardwareInfo)."""

    name: str
    type: str
    plugin: str
    params: dict[str, str]
    joints: tuple[ComponentInfo, ...]
    sensors: tuple[ComponentInfo, ...]
    gpios: tuple[ComponentInfo, ...]
    transmissions: tuple[TransmissionInfo, ...] = ()


@dataclasses.dataclass
class Description:
    """Every `<ros2_control>` block of a description, and what was not understood in them.

    Attributes:
      where: the file (or "ros2_control XML") for messages.
      directory: the folder relative paths in it (pids_config_file) are taken from, or None.
      hardware: one per block, in document order.
      warnings: one line per element or parameter batchsim does not act on.
      document: the whole (xacro-expanded) document the blocks came from, when it was a file
        or text of its own (a URDF), else None.
    """

    where: str
    directory: Path | None
    hardware: list[HardwareInfo]
    warnings: list[str] = dataclasses.field(default_factory=list)
    document: ET.Element | None = None

    @property
    def joints(self) -> list[ComponentInfo]:
        return [j for hw in self.hardware for j in hw.joints]

    @property
    def sensors(self) -> list[ComponentInfo]:
        return [s for hw in self.hardware for s in hw.sensors]

    @property
    def transmissions(self) -> list[TransmissionInfo]:
        return [t for hw in self.hardware for t in hw.transmissions]

    def param(self, name: str) -> tuple[str, HardwareInfo] | None:
        """A hardware param, from the first block that sets it."""
        for hw in self.hardware:
            if name in hw.params:
                return hw.params[name], hw
        return None


def model_file(description: Description) -> str | None:
    """The MJCF a ros2_control file names in its `mujoco_model` hardware param (mujoco_ros2_control
    loads the simulation from it), relative paths taken from the file's folder; None if unset."""
    found = description.param("mujoco_model")
    if found is None or not found[0].strip():
        return None
    path = Path(found[0].strip()).expanduser()
    if not path.is_absolute() and description.directory is not None:
        path = description.directory / path
    return str(path)


def not_text(e: UnicodeDecodeError) -> str:
    """Why a file that should be XML text is not: the byte, where."""
    return f"not a text file (byte 0x{e.object[e.start]:02x} at offset {e.start} is not UTF-8): a robot description is XML text"


def split_source(source: str) -> tuple[str, dict[str, str]]:
    """`"robot.urdf.xacro use_pid:=true name:=x"` -> the path and the xacro arguments."""
    parts = shlex.split(source)
    if not parts:
        return source, {}
    args = {}
    for part in parts[1:]:
        key, sep, value = part.partition(":=")
        if not sep or not key:
            raise ModelError(f"{parts[0]}: xacro argument {part!r} is not key:=value")
        args[key] = value
    return parts[0], args


def read_source(
    source: str | Path, args: dict[str, str] | None = None, *, what: str = "robot description XML"
) -> tuple[str, str, Path | None]:
    """(text, where, path) of a description given as a file path (optionally followed by
    xacro `key:=value` arguments; xacro expanded) or as XML text (`where` is then `what`).

    Raises:
      ModelError: a missing file, a xacro error, or xacro given as text.
    """
    text = str(source)
    if text.lstrip().startswith("<"):
        if XACRO_NS in text:
            raise ModelError(f"{what}: xacro XML must be given as a file (its includes and $(find) need one)")
        return text, what, None
    file, from_source = split_source(text) if isinstance(source, str) else (text, {})
    xacro_args = {**from_source, **(args or {})}
    path = Path(file).expanduser()
    try:
        text = path.read_text()
    except OSError as e:
        raise ModelError(f"{path}: {e.strerror}") from None
    except UnicodeDecodeError as e:
        raise ModelError(f"{path}: {not_text(e)}") from None
    if path.name.endswith(".xacro") or XACRO_NS in text or xacro_args:
        text = expand_xacro(path, xacro_args)
    return text, str(path), path


def read_description(
    source: str | Path, *, args: dict[str, str] | None = None
) -> Description:
    """Every ros2_control block of a URDF/xacro/XML file or of XML text.

    Args:
      source: a file path, optionally followed by xacro `key:=value` arguments, or XML text.
      args: xacro arguments (added to those in `source`).

    Raises:
      ModelError: a missing file, malformed XML, a xacro error, or no <ros2_control> block.
    """
    text, where, path = read_source(source, args, what="ros2_control XML")
    root = parse_xml(text, where)
    elements = [root] if root.tag == "ros2_control" else list(root.iter("ros2_control"))
    if not elements:
        raise ModelError(f"{where}: no <ros2_control> element")
    return from_elements(elements, where, path.parent if path else None, urdf=root)


def parse_xml(text: str, where: str) -> ET.Element:
    try:
        return ET.fromstring(text)
    except ET.ParseError as e:
        line, col = e.position
        raise ModelError(f"{where}:{line}:{col}: malformed XML: {xml_error_reason(e)}") from None


def xml_error_reason(e: ET.ParseError) -> str:
    """An XML parse error without its position, which messages give as file:line:col."""
    return re.sub(r":? line \d+, column \d+$", "", str(e))


def from_elements(
    elements: list[ET.Element], where: str, directory: Path | None, *, urdf: ET.Element | None = None
) -> Description:
    """The blocks of already-parsed `<ros2_control>` elements (inline in an MJCF, or a URDF's)."""
    description = Description(where, directory, [], document=urdf)
    mimics = _urdf_mimics(urdf) if urdf is not None else {}
    for block in elements:
        description.hardware.append(_block(block, where, description.warnings, mimics))
    return description


def _params(el: ET.Element) -> dict[str, str]:
    return {p.get("name", ""): (p.text or "").strip() for p in el.findall("param")}


def _interfaces(el: ET.Element, tag: str) -> tuple[InterfaceInfo, ...]:
    return tuple(InterfaceInfo(i.get("name", ""), _params(i)) for i in el.findall(tag))


def _urdf_mimics(root: ET.Element) -> dict[str, MimicInfo]:
    """URDF `<joint name><mimic joint multiplier offset/></joint>` elements, by joint name."""
    out = {}
    for joint in root.iter("joint"):
        m = joint.find("mimic")
        if m is not None and joint.get("name") and m.get("joint"):
            out[joint.get("name", "")] = MimicInfo(
                m.get("joint", ""), float(m.get("multiplier", 1.0)), float(m.get("offset", 0.0))
            )
    return out


def _block(
    block: ET.Element, where: str, warnings: list[str], urdf_mimics: dict[str, MimicInfo]
) -> HardwareInfo:
    name = block.get("name", "")
    label = f"{where}: ros2_control {name!r}" if name else f"{where}: ros2_control"
    hardware = block.find("hardware")
    plugin, params = "", {}
    if hardware is not None:
        plugin = (hardware.findtext("plugin") or "").strip()
        params = _params(hardware)
        for key in params:
            if key not in HARDWARE_PARAMS and key not in HARDWARE_PARAMS_UNUSED:
                warnings.append(f"{label}: hardware param {key!r}: ignored: batchsim does not know it")
    joints, sensors, gpios, transmissions = [], [], [], []
    for el in block:
        tag = el.tag if isinstance(el.tag, str) else ""
        if tag == "hardware":
            continue
        if tag == "joint":
            joints.append(_joint(el, label, warnings, urdf_mimics))
        elif tag == "sensor":
            sensors.append(ComponentInfo(el.get("name", ""), _params(el), (), _interfaces(el, "state_interface")))
        elif tag == "gpio":
            gpios.append(ComponentInfo(el.get("name", ""), _params(el), _interfaces(el, "command_interface"),
                                       _interfaces(el, "state_interface")))
            warnings.append(f"{label}: gpio {el.get('name', '')!r}: ignored: batchsim has no GPIO interfaces")
        elif tag == "transmission":
            transmissions.append(_transmission(el))
        elif tag.startswith("{"):
            warnings.append(f"{label}: <{tag}>: ignored: an unexpanded xacro element (give the file, not its text)")
        else:
            warnings.append(f"{label}: <{tag}>: ignored: not a ros2_control element")
    return HardwareInfo(
        name, block.get("type", "system"), plugin, params, tuple(joints), tuple(sensors), tuple(gpios),
        tuple(transmissions),
    )


def _transmission(el: ET.Element) -> TransmissionInfo:
    def end(e: ET.Element) -> TransmissionEnd:
        values, bad = {}, ""
        for key, default in (("mechanical_reduction", 1.0), ("offset", 0.0)):
            text = (e.findtext(key) or "").strip()
            try:
                values[key] = float(text) if text else default
            except ValueError:
                values[key], bad = default, f"<{key}> {text!r} is not a number"
        return TransmissionEnd(e.get("name", ""), e.get("role", ""), bad=bad, **values)

    return TransmissionInfo(
        el.get("name", ""),
        (el.findtext("plugin") or el.findtext("type") or "").strip(),
        tuple(end(j) for j in el.findall("joint")),
        tuple(end(a) for a in el.findall("actuator")),
        _params(el),
    )


def _joint(el: ET.Element, label: str, warnings: list[str], urdf_mimics: dict[str, MimicInfo]) -> ComponentInfo:
    name = el.get("name", "")
    params = _params(el)
    mimic = None
    if "mimic" in params:  # mujoco_ros2_control: <param name="mimic">joint</param>, multiplier, offset
        mimic = MimicInfo(params["mimic"], float(params.get("multiplier", 1.0)), float(params.get("offset", 0.0)))
    elif el.get("mimic", "").lower() != "false" and name in urdf_mimics:
        mimic = urdf_mimics[name]  # ros2_control: a URDF <mimic> joint is a mimic joint unless mimic="false"
    for key in params:
        if key not in ("mimic", "multiplier", "offset"):
            warnings.append(f"{label}: joint {name!r}: param {key!r}: ignored: batchsim does not know it")
    commands = _interfaces(el, "command_interface")
    for ci in commands:
        for key in ci.params:
            if key not in ("min", "max", "initial_value"):
                warnings.append(
                    f"{label}: joint {name!r}: command_interface {ci.name!r}: param {key!r}: ignored"
                )
    return ComponentInfo(name, params, commands, _interfaces(el, "state_interface"), mimic)


# --- xacro ---


def expand_xacro(path: Path, args: dict[str, str]) -> str:
    """The URDF a xacro file expands to with `args`, as `xacro FILE key:=value` prints it."""
    try:
        import xacro
    except ModuleNotFoundError:
        raise ModelError(f"{path}: a xacro file needs the xacro package: pip install xacro") from None
    with _find_resolver(path.resolve().parent):
        try:
            doc = xacro.process_file(str(path), mappings=dict(args))
        except Exception as e:  # xacro raises its own and xml.dom's exceptions
            message = " ".join(str(e).split()) or type(e).__name__
            raise ModelError(f"{path}: xacro: {message}") from None
    return doc.toxml()


def resolve_package(pkg: str, directory: Path, ament: Callable[[str], str] | None = None) -> str:
    """A ROS package's folder, as `$(find pkg)` and `package://pkg/` name it: ament's index
    (a sourced ROS), else a folder named `pkg` at or above `directory` (or beside one)."""
    if ament is None:
        from xacro import substitution_args

        ament = substitution_args._eval_find
    try:
        return ament(pkg)
    except Exception:
        pass
    for d in (directory, *directory.parents):
        if d.name == pkg:
            return str(d)
        if (d / pkg).is_dir():
            return str(d / pkg)
    raise ModelError(
        f"$(find {pkg}): no package {pkg!r}: not in ament's index (AMENT_PREFIX_PATH) and no "
        f"folder named {pkg} at or above {directory}"
    )


@contextlib.contextmanager
def _find_resolver(directory: Path) -> Iterator[None]:
    """While expanding, `$(find pkg)` falls back to a folder named `pkg` at or above `directory`."""
    from xacro import substitution_args

    original = substitution_args._eval_find
    substitution_args._eval_find = lambda pkg: resolve_package(pkg, directory, original)  # no hook: restored below
    try:
        yield
    finally:
        substitution_args._eval_find = original
