"""ROS names for a fleet: world namespaces from a template, topic-safe sensor and actuator names.

No rclpy here, so the rules are testable without a ROS graph.

- A world's namespace is the template with `{i}` replaced by the world index
  (`world_{i}` -> `world_3`, `w_{i:03d}` -> `w_003`: format specs work), without leading
  or trailing slashes; two worlds never share one. A single world may have the root
  namespace (template `""` or `/`): its names are then exactly mujoco_ros2_control's
  (`/joint_states`, frames without a prefix). `topic_name()` and `frame()` build every name.
- With one world, the default template, and an MJCF whose `mujoco.ros2` extension block
  sets `ros_namespace`, the namespace is that key's value, so topic names are exactly the
  plugin's (`ros_namespace="car/"` -> `/car/sensors/<sensor>`).
- A ROS name token holds letters, digits and underscores and does not start with a
  digit. MJCF names may hold anything else (`.`, `-`, spaces): each such character
  becomes `_`, a leading digit gets a `_` in front, and a name that then collides with
  another gets `_2`, `_3`, ... appended. `ros_name("wrist.force")` is `wrist_force`.
"""

from __future__ import annotations

import re
import string

from batchsim.basics import OptionError

DEFAULT_TEMPLATE = "world_{i}"

_BAD = re.compile(r"[^A-Za-z0-9_]")
_NS_TOKEN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class NamingError(OptionError):
    """A namespace template or MJCF namespace that cannot make valid, distinct ROS names;
    its `option` is "namespace"."""

    def __init__(self, detail: str, option: str = "namespace"):
        super().__init__(option, detail)


def topic_name(namespace: str, name: str) -> str:
    """The absolute name of `name` in a world's namespace: `/<ns>/<name>`, or `/<name>` at the root."""
    name = name.strip("/")
    return f"/{namespace}/{name}" if namespace else f"/{name}"


def worlds_label(namespaces: list[str], lo: int = 0, hi: int | None = None) -> str:
    """Worlds lo..hi-1 as the log names them: `/world_0 .. /world_63`, or `/world_5` (`/` at the root)."""
    hi = len(namespaces) if hi is None else hi
    return f"/{namespaces[lo]}" if hi - lo == 1 else f"/{namespaces[lo]} .. /{namespaces[hi - 1]}"


def frame(namespace: str, name: str) -> str:
    """A world's tf frame: `<ns>/<name>`, or `<name>` at the root."""
    return f"{namespace}/{name}" if namespace else name


def expand_frame(template: str, namespace: str) -> str:
    """A frame template holding `{ns}` (`"{ns}/odom"`) for a world."""
    return template.replace("{ns}/", frame(namespace, "")).replace("{ns}", namespace)


def ros_name(name: str) -> str:
    """`name` as one valid ROS name token (letters, digits, `_`; no leading digit)."""
    token = _BAD.sub("_", name) or "_"
    if token[0].isdigit():
        token = "_" + token
    return token


def ros_names(names: list[str]) -> list[str]:
    """Each name as a ROS token, made distinct: a collision gets `_2`, `_3`, ... appended."""
    out: list[str] = []
    seen: set[str] = set()
    for name in names:
        token = ros_name(name)
        candidate, k = token, 2
        while candidate in seen:
            candidate, k = f"{token}_{k}", k + 1
        seen.add(candidate)
        out.append(candidate)
    return out


def world_namespaces(
    nworld: int, template: str = DEFAULT_TEMPLATE, plugin_namespace: str | None = None, offset: int = 0
) -> list[str]:
    """One namespace per world, without leading or trailing `/` (`"world_3"`, `"a/b"`).

    Args:
      nworld: number of worlds.
      template: a namespace with `{i}` for the world's number.
      plugin_namespace: the MJCF's `mujoco.ros2` `ros_namespace`; used, when set, for a
        single world whose template is the default (and offset 0).
      offset: the number of the first world: world k gets `{i}` = offset + k, so several
        processes can serve one fleet of distinct namespaces.

    Raises:
      NamingError: a template without `{i}` for several worlds, or one that does not make
        valid ROS namespaces, naming the template and the offending result.
    """
    if nworld == 1 and plugin_namespace and template == DEFAULT_TEMPLATE and offset == 0:
        ns = plugin_namespace.strip("/")
        _check_namespace(ns, f"the MJCF's mujoco.ros2 ros_namespace {plugin_namespace!r}", option="")
        return [ns]
    try:  # fields by name, so that format specs work: 'w_{i:03d}'
        fields = {name for _, name, _, _ in string.Formatter().parse(template) if name is not None}
    except ValueError as e:
        raise NamingError(f"{template!r}: {e}") from None
    if (nworld > 1 or offset) and "i" not in fields:
        raise NamingError(
            f"{template!r} has no {{i}}: {nworld} worlds need distinct namespaces (e.g. 'robot_{{i}}')"
            if nworld > 1
            else f"{template!r} has no {{i}}: a world offset needs it (e.g. 'robot_{{i}}')"
        )
    out = []
    first: dict[str, int] = {}
    for i in range(offset, offset + nworld):
        try:
            ns = template.format(i=i).strip("/")
        except (KeyError, IndexError, ValueError) as e:
            raise NamingError(f"{template!r}: only {{i}} may be substituted ({e})") from None
        if ns == "" and nworld == 1 and not offset:
            out.append(ns)  # the root namespace, for one world
            break
        _check_namespace(ns, f"{template!r} gives {ns!r}, which")
        if first.setdefault(ns, i) != i:  # a spec that truncates or pads away the index
            raise NamingError(
                f"{template!r} gives {ns!r} to several worlds ({first[ns]} and {i}): "
                "each world needs its own namespace"
            )
        out.append(ns)
    return out


def _check_namespace(ns: str, what: str, option: str = "namespace") -> None:
    tokens = ns.split("/")
    if not ns or not all(_NS_TOKEN.match(t) for t in tokens):
        raise NamingError(
            f"{what} is not a valid ROS namespace: use letters, digits and '_' between '/', "
            "not starting with a digit",
            option,
        )
