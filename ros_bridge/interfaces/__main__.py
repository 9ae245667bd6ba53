"""`python -m ros_bridge.interfaces [--force] [--check] [--require]`

Builds (or copies from the cache) the interface packages this interpreter cannot import
yet, into its prefix: one progress line per package. Packages a sourced ROS 2 install
already provides (AMENT_PREFIX_PATH) are left to it. Without cmake/g++ (and no cached
build) it prints one line saying what is missing and what is lost.

  --check    only report what is missing; build nothing
  --force    rebuild from source even if importable or cached (refreshes the cache)
  --require  exit non-zero if any package is still missing at the end (make/CI use it)
  --jobs N   make's -j (default 2)
"""

from __future__ import annotations

import argparse
import concurrent.futures
import importlib
import importlib.util
import subprocess
import sys
import time

from ros_bridge import interfaces
from ros_bridge.interfaces import build

PREFIX = "ros interfaces:"


def _say(text: str) -> None:
    print(f"{PREFIX} {text}", flush=True)


def _levels(packages: list[str]) -> list[list[str]]:
    """`packages` in dependency order, as levels of mutually independent packages."""
    deps = {pkg: [d for d in build.package_deps(pkg) if d in packages] for pkg in packages}
    done: set[str] = set()
    levels = []
    while len(done) < len(packages):
        level = [p for p in packages if p not in done and all(d in done for d in deps[p])]
        if not level:
            raise RuntimeError(f"dependency cycle among {packages}")
        levels.append(level)
        done.update(level)
    return levels


def _one(pkg: str, dest, force: bool, jobs: int) -> str:
    """Build or copy one package into this prefix; return its progress line."""
    start = time.monotonic()
    tree = None if force else build.cached(pkg, dest)
    how = "installed from cache"
    if tree is None:
        tree = build.build(pkg, dest, jobs=jobs)
        how = "built and installed"
    build.install(tree)
    return f"{pkg} {how} in {time.monotonic() - start:.1f} s"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m ros_bridge.interfaces", description=__doc__.splitlines()[2])
    parser.add_argument("--check", action="store_true", help="only report; build nothing")
    parser.add_argument("--force", action="store_true", help="rebuild even if importable or cached")
    parser.add_argument("--require", action="store_true", help="exit non-zero if any package is missing")
    parser.add_argument("--jobs", type=int, default=2, help="make -j (default 2)")
    parser.add_argument("packages", nargs="*", help=f"which packages (default: all of {' '.join(interfaces.PACKAGES)})")
    args = parser.parse_args(argv)
    unknown = set(args.packages) - set(interfaces.PACKAGES)
    if unknown:
        parser.error(f"unknown package(s): {' '.join(sorted(unknown))}")
    packages = [p for p in interfaces.PACKAGES if p in (args.packages or interfaces.PACKAGES)]

    if importlib.util.find_spec("rclpy") is None:
        _say("rclpy is not installed (pip install 'batchsim[ros]'): nothing to build")
        return 1 if args.require else 0

    todo, why = [], ""
    for pkg in packages:
        ros = build.sourced_prefix(pkg)
        if ros is not None:
            _say(f"{pkg} comes from the sourced ROS install {ros}: nothing built")
        elif args.force or not interfaces.available()[pkg]:
            todo.append(pkg)

    if todo and not args.check:
        dest = build.cache_dir()
        uncached = [p for p in todo if args.force or build.cached(p, dest) is None]
        tools = build.missing_tools() if uncached else []
        if tools:
            why = f"{', '.join(tools)} not found"
            todo = [p for p in todo if p not in uncached]
        elif uncached:
            try:
                build.install_build_requirements()
            except subprocess.CalledProcessError:
                why = "pip could not install the build requirements"
                todo = [p for p in todo if p not in uncached]
        failed = _run(todo, dest, args.force, args.jobs)
        if failed:
            _say(f"{', '.join(failed)} failed to build")

    importlib.invalidate_caches()
    line = interfaces.missing_line(why)
    if line:
        print(f"{PREFIX} {line}", file=sys.stderr, flush=True)
        return 1 if args.require else 0
    if not todo:
        _say("all present (" + ", ".join(packages) + ")")
    return 0


def _run(todo: list[str], dest, force: bool, jobs: int) -> list[str]:
    """Build/copy `todo`, level by level, two packages at a time; return the failed ones."""
    failed = []
    with concurrent.futures.ThreadPoolExecutor(max_workers=2) as pool:
        for level in _levels(todo):
            futures = {pool.submit(_one, pkg, dest, force, jobs): pkg for pkg in level}
            for future in concurrent.futures.as_completed(futures):
                try:
                    _say(future.result())
                except (build.BuildError, OSError) as error:
                    _say(str(error))
                    failed.append(futures[future])
    return failed


if __name__ == "__main__":
    sys.exit(main())
