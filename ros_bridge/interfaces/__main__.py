"""`python -m ros_bridge.interfaces [--force] [--check] [--require]`

Builds (or copies from the cache) the interface packages this interpreter cannot import
yet, into its prefix: a line as each stage of each package starts, a "still ..., N s" line
every 10 s while one runs (pip, cmake, make, or waiting for another build of the same cache
to finish that package, which is then taken from the cache, not built again), and one line
per package at the end. Packages a sourced ROS 2 install already provides
(AMENT_PREFIX_PATH) are left to it. Without cmake/g++ (and no cached build) it prints one
line saying what is missing and what is lost; a failed stage is named with its last lines
of output and its log. BATCHSIM_INTERFACES_CACHE moves the cache (see build.py).

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
import sys
import time

from ros_bridge import interfaces
from ros_bridge.interfaces import build

PREFIX = build.PREFIX
_say = build.say


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


def _one(pkg: str, dest, force: bool, jobs: int, since: float) -> str:
    """Build or copy one package into this prefix, holding its cache lock; return its last line."""
    start = time.monotonic()
    with build.package_lock(pkg, dest) as waited:
        tree, built = build.obtain(pkg, dest, jobs=jobs, force=force, since=since)
        build.install(tree)
    if built:
        how = "built and installed"
    elif waited:
        how = "installed from the cache, which another build filled while this one waited"
    else:
        how = "installed from cache"
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
                build.install_build_requirements(dest)
            except (build.BuildError, OSError) as error:
                _say(str(error))
                why = error.short() if isinstance(error, build.BuildError) else f"build requirements: {error}"
                todo = [p for p in todo if p not in uncached]
        failed = _run(todo, dest, args.force, args.jobs)
        if failed:
            _say(f"{', '.join(failed)} failed to build")
            why = "; ".join(filter(None, [why, *failed.values()]))

    importlib.invalidate_caches()
    line = interfaces.missing_line(why)
    if line:
        print(f"{PREFIX} {line}", file=sys.stderr, flush=True)
        return 1 if args.require else 0
    if not todo:
        _say("all present (" + ", ".join(packages) + ")")
    return 0


def _run(todo: list[str], dest, force: bool, jobs: int) -> dict[str, str]:
    """Build/copy `todo`, level by level, two packages at a time; return the failed ones, each
    with one line on why (the failed stage and its log)."""
    since = time.time()  # --force: a tree another run finishes after this is fresh enough to take
    failed = {}
    with concurrent.futures.ThreadPoolExecutor(max_workers=2) as pool:
        for level in _levels(todo):
            futures = {pool.submit(_one, pkg, dest, force, jobs, since): pkg for pkg in level}
            for future in concurrent.futures.as_completed(futures):
                pkg = futures[future]
                try:
                    _say(future.result())
                except build.BuildError as error:
                    _say(str(error))
                    failed[pkg] = error.short()
                except OSError as error:  # copying into the cache or the prefix
                    _say(f"{pkg}: {error}")
                    failed[pkg] = f"{pkg}: {error}"
    return failed


if __name__ == "__main__":
    sys.exit(main())
