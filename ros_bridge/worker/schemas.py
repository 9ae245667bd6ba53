"""A message type's complete definition as rosbag2 writes it into MCAP, and its QoS metadata.

rosbag2's `ros2msg` encoding (rosbag2's docs/message_definition_encoding.md): the type's own
.msg text first, then every type it depends on, recursively, each after a line of 80 `=`
and a line `MSG: <package>/msg/<Name>`. The .msg files come from the installed interface
packages: a sourced ROS install's (AMENT_PREFIX_PATH), the PyPI wheels' (`<venv>/share`), or
the definitions batchsim builds the missing packages from (ros_bridge/interfaces/definitions).
"""

from __future__ import annotations

import functools
import os
import re
import sys
from pathlib import Path

DELIMITER = "=" * 80
PRIMITIVES = {
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32", "uint32",
    "int64", "uint64", "string", "wstring",
}  # fmt: skip
_FIELD = re.compile(r"^\s*([A-Za-z][\w/]*)(?:\[[^\]]*\])?\s+\w+")
_DEFINITIONS = Path(__file__).resolve().parent.parent / "interfaces" / "definitions"


def share_dirs() -> list[Path]:
    """Where interface packages keep their .msg files, in the order they win."""
    dirs = [Path(p) / "share" for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    return [*dirs, Path(sys.prefix) / "share", _DEFINITIONS]


@functools.cache
def msg_text(type_name: str) -> str:
    """The .msg text of "pkg/msg/Name"; LookupError naming where it was looked for."""
    package, _, name = type_name.split("/")
    for root in share_dirs():
        path = root / package / "msg" / f"{name}.msg"
        if path.is_file():
            return path.read_text()
    raise LookupError(f"no definition of {type_name} (looked in {', '.join(str(d) for d in share_dirs())})")


def dependencies(type_name: str, text: str) -> list[str]:
    """The "pkg/msg/Name" of every non-primitive field type of one .msg text, in order."""
    package = type_name.split("/")[0]
    out: list[str] = []
    for line in text.splitlines():
        line = line.split("#", 1)[0]
        match = _FIELD.match(line)
        if match is None or re.match(r"^\s*\S+\s+\w+\s*=", line):
            continue  # a comment, a blank, or a constant
        base = match.group(1)
        if base in PRIMITIVES:
            continue
        if base == "Header":
            base = "std_msgs/Header"
        parts = base.split("/")
        full = f"{parts[0]}/msg/{parts[-1]}" if len(parts) > 1 else f"{package}/msg/{base}"
        if full not in out:
            out.append(full)
    return out


@functools.cache
def schema_text(type_name: str) -> str:
    """The complete ros2msg definition of "pkg/msg/Name", dependencies depth-first, each once."""
    parts = [msg_text(type_name).rstrip("\n")]
    seen = {type_name}
    todo = dependencies(type_name, parts[0])
    while todo:
        dep = todo.pop(0)
        if dep in seen:
            continue
        seen.add(dep)
        text = msg_text(dep).rstrip("\n")
        parts.append(f"{DELIMITER}\nMSG: {dep}\n{text}")
        todo = dependencies(dep, text) + todo
    return "\n".join(parts) + "\n"


def qos_metadata(transient_local: bool = False, depth: int = 10, reliable: bool = True) -> str:
    """rosbag2's `offered_qos_profiles` for a channel (its YAML, the numeric policies every
    rosbag2 since Foxy reads): what the recorded publishers offered."""
    return (
        f"- history: 1\n  depth: {depth}\n  reliability: {1 if reliable else 2}\n"
        f"  durability: {1 if transient_local else 2}\n"
        "  deadline:\n    sec: 0\n    nsec: 0\n  lifespan:\n    sec: 0\n    nsec: 0\n"
        "  liveliness: 1\n  liveliness_lease_duration:\n    sec: 0\n    nsec: 0\n"
        "  avoid_ros_namespace_conventions: false\n"
    )
