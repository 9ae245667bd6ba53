"""The `<ros2_control>` block a real robot's URDF carries: which joints, interfaces and
sensors are exposed, and where joints start (`initial_value`).

Problems with it (a joint the model lacks, a command interface no actuator serves) are
collected, not raised: `on_configure` reports them, as a hardware component does in
ros2_control.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

from batchsim.model.spec import CommandInterface, InterfaceKind, Joint, ModelError, Sensor


def block_of(source: str | Path) -> ET.Element:
    """The <ros2_control> element of a file or of XML text."""
    text = str(source)
    where = "ros2_control XML"
    if not text.lstrip().startswith("<"):
        path = Path(text).expanduser()
        try:
            text = path.read_text()
        except OSError as e:
            raise ModelError(f"{path}: {e.strerror}") from None
        where = str(path)
    try:
        root = ET.fromstring(text)
    except ET.ParseError as e:
        line, col = e.position
        raise ModelError(f"{where}:{line}:{col}: malformed XML: {xml_error_reason(e)}") from None
    block = root if root.tag == "ros2_control" else root.find(".//ros2_control")
    if block is None:
        raise ModelError(f"{where}: no <ros2_control> element")
    return block


def narrow(
    block: ET.Element,
    joints: list[Joint],
    commands: list[CommandInterface],
    sensors: list[Sensor],
    problems: list[str],
    initial: dict[str, float],
) -> tuple[list[Joint], dict[str, list[str]], list[CommandInterface], list[Sensor]]:
    """Keep what a ros2_control block lists; record what it asks for and the model lacks."""
    by_name = {j.name: j for j in joints}
    kinds = [k.value for k in InterfaceKind]
    kept_joints: list[Joint] = []
    joint_states: dict[str, list[str]] = {}
    kept_commands: list[CommandInterface] = []
    for el in block.findall("joint"):
        jname = el.get("name", "")
        if jname not in by_name:
            problems.append(
                f"ros2_control joint {jname!r}: the model has no hinge or slide joint of that name"
            )
            continue
        kept_joints.append(by_name[jname])
        states = []
        for si in el.findall("state_interface"):
            iname = si.get("name", "")
            if iname not in kinds:
                problems.append(
                    f"ros2_control joint {jname!r}: unknown state interface {iname!r} "
                    f"(known: {', '.join(kinds)})"
                )
                continue
            states.append(iname)
            value = _param(si, "initial_value")
            if iname == "position" and value is not None:
                initial[jname] = value
        joint_states[jname] = states
        for ci in el.findall("command_interface"):
            iname = ci.get("name", "")
            match = [c for c in commands if c.joint == jname and c.kind.value == iname]
            if not match:
                served = [c.kind.value for c in commands if c.joint == jname]
                problems.append(
                    f"ros2_control joint {jname!r}: no actuator serves command interface "
                    f"{jname}/{iname} (actuators on this joint serve: "
                    f"{', '.join(served) or 'none'})"
                )
                continue
            kept_commands.extend(match)
    kept_joints.sort(key=lambda j: j.id)
    kept_commands.sort(key=lambda c: c.actuator_id)

    listed = block.findall("sensor")
    if listed:
        names = {s.name: s for s in sensors}
        kept_sensors = []
        for el in listed:
            sname = el.get("name", "")
            if sname not in names:
                problems.append(f"ros2_control sensor {sname!r}: the model has no sensor of that name")
            else:
                kept_sensors.append(names[sname])
        sensors = sorted(kept_sensors, key=lambda s: s.adr)
    return kept_joints, joint_states, kept_commands, sensors


def _param(el: ET.Element, name: str) -> float | None:
    for p in el.findall("param"):
        if p.get("name") == name and p.text is not None:
            try:
                return float(p.text)
            except ValueError:
                return None
    return None


def xml_error_reason(e: ET.ParseError) -> str:
    """An XML parse error without its position, which messages give as file:line:col."""
    # "mismatched tag: line 3, column 2" -> "mismatched tag"
    return re.sub(r":? line \d+, column \d+$", "", str(e))
