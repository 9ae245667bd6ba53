"""The layering DESIGN.md draws, checked on the sources: imports point down only (no cycle,
counting every import a module names, in functions and `if TYPE_CHECKING:` blocks too, between
modules and between batchsim's rooms), rclpy and the ROS message packages only in the bridge
workers, JAX and Warp only in the backends, the engines never import the contract, the core
never imports the bridge (the command line, the top floor, composes both), and no module over
500 lines. Read with `ast`, nothing imported."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("batchsim", "ros_bridge")
ROS = {
    "rclpy", "sensor_msgs", "std_msgs", "std_srvs", "geometry_msgs", "nav_msgs", "tf2_msgs", "control_msgs",
    "controller_manager_msgs", "mujoco_ros2_control_msgs", "rosgraph_msgs", "builtin_interfaces",
    "trajectory_msgs", "diagnostic_msgs", "action_msgs", "rcl_interfaces", "unique_identifier_msgs",
}  # fmt: skip
GPU = {"jax", "jaxlib", "warp", "mujoco_warp"}


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            if "definitions" in f.parts:  # upstream's interface files, not modules
                continue
            parts = f.relative_to(ROOT).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = f
    return out


MODULES = _modules()


def _imports(name: str, path: Path, *, at_import_time: bool) -> list[str]:
    """The modules `name` imports: every one, or only those its import runs (module level,
    `if TYPE_CHECKING:` blocks left out). `from pkg import sub` names pkg.sub, not pkg."""
    tree = ast.parse(path.read_text())
    if at_import_time:  # what runs at import: not function bodies, not `if TYPE_CHECKING:`
        nodes, todo = [], list(tree.body)
        while todo:
            node = todo.pop()
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                continue
            if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
                continue
            nodes.append(node)
            todo += list(ast.iter_child_nodes(node))
    else:
        nodes = list(ast.walk(tree))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: list[str] = []
    for node in nodes:
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([node.module] if node.module else []))
            subs = [f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in MODULES]
            out += subs if len(subs) == len(node.names) else [base, *subs]
    return out


def _offenders(allowed, forbidden_tops: set[str]) -> list[str]:
    return [
        f"{MODULES[name].relative_to(ROOT)} imports {imp}"
        for name in MODULES
        if not allowed(name)
        for imp in _imports(name, MODULES[name], at_import_time=False)
        if imp.split(".")[0] in forbidden_tops or (forbidden_tops is GPU and imp.startswith("mujoco.mjx"))
    ]


def test_only_the_bridge_workers_import_rclpy_or_ros_messages():
    assert _offenders(lambda n: n.startswith("ros_bridge.worker"), ROS) == []


def test_only_the_backends_import_jax_or_warp():
    assert _offenders(lambda n: n.startswith("batchsim.backends"), GPU) == []


def test_the_core_never_imports_the_bridge():
    offenders = [
        f"{MODULES[name].relative_to(ROOT)} imports {imp}"
        for name in MODULES
        if name.startswith("batchsim") and not name.startswith("batchsim.cli")
        for imp in _imports(name, MODULES[name], at_import_time=False)
        if imp.split(".")[0] == "ros_bridge"
    ]
    assert offenders == []


def test_the_model_is_a_floor_below_sensors_backends_and_the_loop():
    """batchsim.model (MJCF, descriptions, the lidars an MJCF declares) needs nothing above it:
    sensors, the contract, the backends and the loop all read the model, never the reverse."""
    below = ("batchsim.model", "batchsim.pid", "batchsim.types")
    offenders = [
        f"{MODULES[name].relative_to(ROOT)} imports {imp}"
        for name in MODULES
        if name.startswith("batchsim.model")
        for imp in _imports(name, MODULES[name], at_import_time=False)
        if imp.startswith("batchsim") and not imp.startswith(below)
    ]
    assert offenders == []


def _cycles(graph: dict[str, list[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components of more than one node: the import cycles."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return cycles


def _graph(*, at_import_time: bool) -> dict[str, list[str]]:
    return {
        name: sorted({m for m in _imports(name, path, at_import_time=at_import_time) if m in MODULES and m != name})
        for name, path in MODULES.items()
    }


def test_no_import_cycle_at_import_time():
    assert _cycles(_graph(at_import_time=True)) == []


def test_no_import_cycle_at_all():
    """Counting every import a module names (in functions, under TYPE_CHECKING): a reader and a
    drawing of the imports see what the code needs, and none of it runs back up."""
    assert _cycles(_graph(at_import_time=False)) == []


def _room(module: str) -> str:
    """The room of a batchsim module, as a drawing of batchsim/ shows it: a subpackage as one
    room (batchsim.backends), a module at the root as its own (batchsim.hardware)."""
    parts = module.split(".")
    if len(parts) == 1:
        return module
    if (ROOT / "batchsim" / parts[1]).is_dir():
        return ".".join(parts[:2])
    return module


def test_batchsims_rooms_import_each_other_in_no_cycle():
    """batchsim/ drawn with its folders as rooms: no room imports one that imports it back
    (the contract above its parts and engines, the loop above the contract, ...)."""
    rooms: dict[str, set[str]] = {}
    for name, targets in _graph(at_import_time=False).items():
        if name.startswith("batchsim") and name != "batchsim":
            here = _room(name)
            rooms.setdefault(here, set())
            rooms[here] |= {_room(t) for t in targets if t.startswith("batchsim.") and _room(t) != here}
    assert _cycles({room: sorted(targets & set(rooms)) for room, targets in rooms.items()}) == []


def test_the_engines_never_import_the_contract():
    """Imports point down: the contract owns an engine (batchsim.engine); no backend imports
    batchsim.hardware, the one concrete system, nor anything that does (the loop, the fleet files)."""
    above = ("batchsim.hardware", "batchsim.loop", "batchsim.cli", "batchsim.controllers", "batchsim.fleet")
    offenders = [
        f"{MODULES[name].relative_to(ROOT)} imports {imp}"
        for name in MODULES
        if name.startswith("batchsim.backends")
        for imp in _imports(name, MODULES[name], at_import_time=False)
        if imp == "batchsim" or imp.startswith(above)
    ]
    assert offenders == []


def test_the_wheels_packages_are_the_folders_with_an_init():
    """setup.py finds the packages: every folder of batchsim/ and ros_bridge/ with an __init__.py
    (batchsim.models aside, which lives in models/), and no folder of modules without one."""
    from setuptools import find_packages

    found = set(find_packages(str(ROOT), include=["batchsim*", "ros_bridge*"]))
    folders = {
        ".".join(d.relative_to(ROOT).parts)
        for pkg in PACKAGES
        for d in [ROOT / pkg, *(ROOT / pkg).rglob("*")]
        if d.is_dir() and any(d.glob("*.py")) and "definitions" not in d.parts and "__pycache__" not in d.parts
    }
    assert found == folders
    assert all((ROOT / p.replace(".", "/") / "__init__.py").exists() for p in found)


def test_no_module_over_500_lines():
    long = {str(p.relative_to(ROOT)): n for p in MODULES.values() if (n := len(p.read_text().splitlines())) > 500}
    assert long == {}


def test_the_checks_see_what_they_check():
    """A check that reads nothing passes for nothing: the rules above must find the imports
    they look for where those are allowed."""
    assert any("rclpy" in i for i in _imports("ros_bridge.worker.core", MODULES["ros_bridge.worker.core"], at_import_time=False))
    warp = [n for n in MODULES if n.startswith("batchsim.backends.warp")]
    assert any(i.split(".")[0] == "warp" for n in warp for i in _imports(n, MODULES[n], at_import_time=False))
    assert "batchsim.loop" in _imports("batchsim.cli.runner", MODULES["batchsim.cli.runner"], at_import_time=True)
    assert len(MODULES) > 100
