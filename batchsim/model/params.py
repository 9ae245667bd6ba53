"""ROS 2 parameter files (`node: ros__parameters: ...` YAML), read as rcl's parser reads them.

One difference from a plain `yaml.safe_load` matters for files written for ROS: a key given
twice in one mapping (mujoco_ros2_control's PID files write `pid_gains:` once for
`position:` and again for `velocity:`) is merged, as rcl merges parameter paths, instead of
the second silently replacing the first. A scalar given twice keeps the last value.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml


class _MergingLoader(yaml.SafeLoader):
    """SafeLoader whose mappings merge a repeated key instead of overwriting it."""


def _construct_mapping(loader: _MergingLoader, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
    loader.flatten_mapping(node)
    out: dict[Any, Any] = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        value = loader.construct_object(value_node, deep=True)
        if key in out and isinstance(out[key], dict) and isinstance(value, dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = value
    return out


_MergingLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def merge(a: Mapping[Any, Any], b: Mapping[Any, Any]) -> dict[Any, Any]:
    """`b` merged into a copy of `a`, nested mappings recursively; `b` wins for scalars."""
    out = dict(a)
    for k, v in b.items():
        if k in out and isinstance(out[k], Mapping) and isinstance(v, Mapping):
            out[k] = merge(out[k], v)
        else:
            out[k] = v
    return out


class ParamsError(ValueError):
    """A parameter file that cannot be read: one line naming the file (and line) and cause."""


def load_yaml(text: str, where: str) -> Any:
    """YAML text as rcl reads it (repeated keys merged); ParamsError names `where`:line:col."""
    try:
        return yaml.load(text, Loader=_MergingLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        at = f":{mark.line + 1}:{mark.column + 1}" if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise ParamsError(f"{where}{at}: malformed YAML: {problem}") from None


def read_yaml(path: str | Path) -> Any:
    """A YAML file as rcl reads it; ParamsError for a missing file or malformed YAML."""
    path = Path(path).expanduser()
    return load_yaml(read_text(path, str(path)), str(path))


def read_text(path: Path, where: str) -> str:
    """A YAML file's text; ParamsError naming `where` for one that cannot be read or is not UTF-8 text."""
    try:
        return path.expanduser().read_text()
    except OSError as e:
        raise ParamsError(f"{where}: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise ParamsError(
            f"{where}: not a text file (byte 0x{e.object[e.start]:02x} at offset {e.start} is not UTF-8): YAML is text"
        ) from None


def node_parameters(doc: Any, node: str | None, where: str) -> dict[str, Any]:
    """The `ros__parameters` that apply to `node` in a parameter file: those under `/**`, a
    `/**/<node>` or `<node>` key, merged in that order; every node's if `node` is None."""
    if not isinstance(doc, Mapping):
        raise ParamsError(f"{where}: expected a mapping of node names to ros__parameters")
    out: dict[str, Any] = {}
    for key, value in doc.items():
        name = str(key).rstrip("/").rsplit("/", 1)[-1]
        if node is not None and name not in ("**", node):
            continue
        params = value.get("ros__parameters") if isinstance(value, Mapping) else None
        if not isinstance(params, Mapping):
            raise ParamsError(f"{where}: {key}: expected a ros__parameters: block")
        out = merge(out, params)
    return out


def nest_dotted(values: Mapping[str, Any]) -> dict[str, Any]:
    """`{"a.b.c": 1}` -> `{"a": {"b": {"c": 1}}}`; ROS writes a parameter either way."""
    out: dict[str, Any] = {}
    for key, value in values.items():
        if isinstance(value, Mapping):
            value = nest_dotted(value)
        parts = str(key).split(".")
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                break
        else:
            last = parts[-1]
            if last in node and isinstance(node[last], dict) and isinstance(value, dict):
                node[last] = merge(node[last], value)
            else:
                node[last] = value
    return out
