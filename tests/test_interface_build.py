"""How `python -m ros_bridge.interfaces` builds into its cache (issue 46): runs at the same time
share one cache, a failure names its stage and log, and a long stage prints progress.

What is real: `ros_bridge.interfaces` itself, in processes of its own: `__main__._run` and
`main` (two packages at a time), the per-package flock, the look into the cache after
taking it, the scratch directory inside the cache and the rename of the finished tree,
the stages run as subprocesses with their output in the package's log, the progress lines,
the error messages and the `Fix:` line. What is fake: `cmake` and `make` (and `g++`, `gcc`,
which are only looked for), which come first on PATH: tests/ writes them as one Python
script that lays out a package's install tree (`share/<pkg>/package.xml` and a Python
package) in a second instead of compiling it for minutes, records each package it
"builds", and sleeps, fails or crashes where the test says. And `build.install`, which
would copy into this venv: here it only records the tree. The cache is a tmp dir
(BATCHSIM_INTERFACES_CACHE; XDG_CACHE_HOME points at another, so not even an older
`build.py`, which knows only that one, can reach ~/.cache).
"""

from __future__ import annotations

import fcntl
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from conftest import need

from ros_bridge import interfaces
from ros_bridge.interfaces import build, stages

# over a few seconds each: `make test` runs them, `make quick` leaves them out
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]

# cmake, make, g++ and gcc in one: a package's install tree in a second, its "build" counted in $FAKE_BUILDS
FAKE_TOOL = r"""
import json, os, re, shutil, sys, time
from pathlib import Path

tool, args = Path(sys.argv[0]).name, sys.argv[1:]
if tool == "cmake":
    src, work = Path(args[args.index("-S") + 1]), Path(args[args.index("-B") + 1])
    prefix = next(a.split("=", 1)[1] for a in args if a.startswith("-DCMAKE_INSTALL_PREFIX="))
    pkg = re.search(r"project\((\w+)\)", (src / "CMakeLists.txt").read_text()).group(1)
    work.mkdir(parents=True)
    (work / "fake.json").write_text(json.dumps({"pkg": pkg, "src": str(src), "prefix": prefix}))
    print("-- The CXX compiler identification is fake\n-- Configuring done\n-- Generating done")
elif tool == "make":
    conf = json.loads((Path(args[args.index("-C") + 1]) / "fake.json").read_text())
    pkg, prefix = conf["pkg"], Path(conf["prefix"])
    if "install" in args:
        share = prefix / "share" / pkg
        share.mkdir(parents=True)
        shutil.copy(Path(conf["src"]) / "package.xml", share)
        site = prefix / "lib" / f"python{sys.version_info[0]}.{sys.version_info[1]}" / "site-packages" / pkg
        site.mkdir(parents=True)
        (site / "__init__.py").write_text("")
        with open(os.environ["FAKE_BUILDS"], "a") as f:
            f.write(f"{pkg} {os.getppid()}\n")
        print(f"-- Installing: {share}/package.xml")
    else:
        for i in range(30):
            print(f"[{i * 3:3d}%] Building CXX object CMakeFiles/{pkg}/fake_{i}.cpp.o")
        sys.stdout.flush()
        if pkg == os.environ.get("FAKE_CRASH"):
            os.kill(os.getppid(), 9)  # the build process dies here, as on a power cut or kill -9
        time.sleep(float(os.environ.get("FAKE_BUILD_S", "1")))
        if pkg == os.environ.get("FAKE_FAIL"):
            print(f"fake_7.cpp:1:10: fatal error: {pkg}/msg/detail/missing.hpp: No such file or directory")
            print("make[2]: *** [CMakeFiles/fake.dir/build.make:77: fake_7.cpp.o] Error 1")
            sys.exit(2)
"""

# runs in a process of its own: the real _run or main, with build.install only recording
RUNNER = r"""
import os, sys, time
from ros_bridge import interfaces
from ros_bridge.interfaces import __main__ as cli, build

installed = []
build.install = lambda tree, prefix=None: installed.append(str(tree))  # not into this venv
mode, args = sys.argv[1], sys.argv[2:]
print("ready", flush=True)
while os.environ.get("GO_FILE") and not os.path.exists(os.environ["GO_FILE"]):
    time.sleep(0.01)  # start together with the other run
if mode == "run":
    force = "--force" in args
    packages = [a for a in args if a != "--force"] or list(interfaces.PACKAGES)
    failed = cli._run(packages, build.cache_dir(), force, 2)
    print("installed:", *installed, flush=True)
    sys.exit(1 if failed else 0)
else:  # main, as on a venv that lacks control_msgs and has its build requirements
    interfaces.available = lambda: {p: p != "control_msgs" for p in interfaces.PACKAGES}
    build.install_build_requirements = lambda dest=None: None
    sys.exit(cli.main(args))
"""


def _env(tmp_path: Path, **extra: str) -> dict[str, str]:
    """The fake tools first on PATH, the cache in tmp_path/cache."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    for tool in ("cmake", "make", "g++", "gcc"):
        path = bin_dir / tool
        path.write_text(f"#!{sys.executable}\n{FAKE_TOOL}")
        path.chmod(0o755)
    if shutil.which("cmake", path=os.path.join(sys.prefix, "bin")):  # build_env() puts the venv's bin first
        pytest.skip("this venv has a cmake of its own, which would shadow the fake one")
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}",
           "BATCHSIM_INTERFACES_CACHE": str(tmp_path / "cache"), "XDG_CACHE_HOME": str(tmp_path / "xdg"),
           "FAKE_BUILDS": str(tmp_path / "builds.txt"), "PYTHONUNBUFFERED": "1"}
    env.pop("AMENT_PREFIX_PATH", None)  # no sourced ROS install to defer to
    env.pop("BATCHSIM_INTERFACES_PROGRESS_S", None)
    return {**env, **extra}


def _runner(env: dict[str, str], *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", RUNNER, *args], cwd=ROOT, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


def _cache(tmp_path: Path) -> Path:
    return tmp_path / "cache" / build.cache_key()


def _builds(tmp_path: Path) -> list[str]:
    """The packages the fake make installed, one entry per build."""
    path = tmp_path / "builds.txt"
    return sorted(line.split()[0] for line in path.read_text().splitlines()) if path.exists() else []


@pytest.mark.parametrize("force", [False, True], ids=["plain", "force"])
def test_two_runs_at_once_into_one_empty_cache_build_each_package_once(tmp_path, force):
    """Two runs started at the same instant (as two checkouts or CI jobs under one HOME) into
    one empty cache: both succeed, each package is built once, by whichever run took its lock
    first, and the other waits and takes it from the cache (with --force too: a tree finished
    after that run started is fresh enough). No scratch directory is left in the cache."""
    go = tmp_path / "go"
    env = _env(tmp_path, GO_FILE=str(go))
    runs = [_runner(env, "run", *(["--force"] if force else [])) for _ in range(2)]
    for run in runs:
        assert run.stdout.readline().strip() == "ready"
    go.touch()
    outs = [run.communicate(timeout=180)[0] for run in runs]
    assert [run.returncode for run in runs] == [0, 0], "\n".join(outs)

    assert _builds(tmp_path) == sorted(interfaces.PACKAGES), "\n".join(outs)  # each exactly once
    cache = _cache(tmp_path)
    for pkg in interfaces.PACKAGES:
        assert build.cached(pkg, cache) == cache / pkg
        built = [out for out in outs if f"ros interfaces: {pkg} built and installed" in out]
        taken = [out for out in outs if f"ros interfaces: {pkg} installed from" in out]  # as a rule after waiting
        assert (len(built), len(taken)) == (1, 1), "\n".join(outs)
    assert "waiting for another build's lock" in "".join(outs)
    assert "installed from the cache, which another build filled while this one waited" in "".join(outs)
    for out in outs:  # each run installs every package, from the one tree in the cache
        installed = next(line for line in out.splitlines() if line.startswith("installed:")).split()[1:]
        assert sorted(installed) == sorted(str(cache / pkg) for pkg in interfaces.PACKAGES)
    assert sorted(p.name for p in cache.iterdir() if p.name.startswith(".")) == []  # no scratch or tmp left


def test_a_failed_build_names_its_stage_last_lines_and_log(tmp_path, monkeypatch):
    """A failing `make` (cmake, make, g++ and gcc all on PATH): the error names the package
    and the stage, shows the compiler's error line, and names the log holding the whole
    output; the closing `Fix:` line does not send the user to install cmake or g++. Only
    where a tool really is missing does the Fix line name it (and only it)."""
    need("rclpy", "run `pip install 'batchsim[ros]'`")  # main() builds nothing without rclpy
    env = _env(tmp_path, FAKE_FAIL="control_msgs")
    done = subprocess.run([sys.executable, "-c", RUNNER, "main", "--require"], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=180)
    out = done.stdout + done.stderr
    assert done.returncode == 1, out
    log = _cache(tmp_path) / "control_msgs.log"
    assert "ros interfaces: control_msgs: build (make -j2) failed" in done.stdout, out
    assert "fatal error: control_msgs/msg/detail/missing.hpp: No such file or directory" in done.stdout, out
    assert f"the whole output: {log}" in done.stdout, out
    whole = log.read_text()
    assert "-- Configuring done" in whole and "missing.hpp" in whole  # every stage, not just the last lines
    line = next(line for line in done.stderr.splitlines() if "ROS interface packages" in line)
    assert "control_msgs missing (control_msgs: build (make -j2) failed, log " + str(log) in line, line
    fix = line.split("Fix:", 1)[1]
    assert "cmake" not in fix and "g++" not in fix, line
    assert build.cached("control_msgs", _cache(tmp_path)) is None
    assert not [p for p in _cache(tmp_path).iterdir() if p.name.endswith(".tmp")]  # its scratch dir went too

    monkeypatch.setattr(interfaces, "available", lambda: {p: p != "tf2_msgs" for p in interfaces.PACKAGES})
    monkeypatch.setattr(shutil, "which", lambda tool, *a, **k: None if tool == "g++" else f"/usr/bin/{tool}")
    fix = interfaces.missing_line().split("Fix:", 1)[1]
    assert "install g++, then" in fix and "cmake" not in fix, fix
    monkeypatch.setattr(shutil, "which", lambda tool, *a, **k: f"/usr/bin/{tool}")
    fix = interfaces.missing_line().split("Fix:", 1)[1]
    assert "g++" not in fix and "cmake" not in fix, fix


@pytest.mark.timing
def test_a_line_at_least_every_interval_while_waiting_and_building(tmp_path, monkeypatch):
    """Progress while another build holds the package's lock (the test holds it 3 s) and
    while a 4 s `make` runs, with the interval set to 1 s (BATCHSIM_INTERFACES_PROGRESS_S;
    10 s by default): a line as each stage starts, "still ..., N s" lines in between, and
    never more than 3 intervals without a line, from the first line to the last."""
    env = _env(tmp_path, FAKE_BUILD_S="4", BATCHSIM_INTERFACES_PROGRESS_S="1")
    cache = _cache(tmp_path)
    cache.mkdir(parents=True)
    lines = []
    with open(cache / "tf2_msgs.lock", "a+") as held:
        fcntl.flock(held, fcntl.LOCK_EX)  # another build has tf2_msgs
        run = _runner(env, "run", "tf2_msgs")
        release = threading.Timer(3, fcntl.flock, (held, fcntl.LOCK_UN))
        for line in run.stdout:
            lines.append((time.monotonic(), line.rstrip()))
            if "waiting for another build's lock" in line and not release.ident:
                release.start()  # 3 s after the run starts waiting
        if release.ident:
            release.join()
    assert run.wait(60) == 0, "\n".join(line for _, line in lines)
    text = "\n".join(line for _, line in lines)
    assert "ros interfaces: tf2_msgs: waiting for another build's lock" in text, text
    assert len(re.findall(r"tf2_msgs: still waiting for another build's lock, \d+ s", text)) >= 2, text
    for stage in ("cmake configure", "build (make -j2)", "make install"):
        assert f"ros interfaces: tf2_msgs: {stage} ..." in text, text
    still = [int(s) for s in re.findall(r"tf2_msgs: still build \(make -j2\), (\d+) s", text)]
    assert len(still) >= 3 and still == sorted(still), text
    assert "ros interfaces: tf2_msgs built and installed" in text
    progress = [t for t, line in lines if line.startswith("ros interfaces:")]
    gaps = [b - a for a, b in zip(progress, progress[1:], strict=False)]
    assert max(gaps) < 3, (gaps, text)
    monkeypatch.delenv("BATCHSIM_INTERFACES_PROGRESS_S", raising=False)
    assert stages.progress_interval() == 10  # by default: a line at least every 10 s


def test_a_crashed_build_leaves_nothing_in_the_way(tmp_path):
    """A build killed mid-make (kill -9) leaves its scratch directory in the cache and no tree;
    the next run removes it, replaces an incomplete tree that an older build left (no
    package.xml), builds and puts a complete one in place."""
    crashed = subprocess.run([sys.executable, "-c", RUNNER, "run", "tf2_msgs"], cwd=ROOT,
                             env=_env(tmp_path, FAKE_CRASH="tf2_msgs"), capture_output=True, text=True, timeout=120)
    assert crashed.returncode == -9, crashed.stdout + crashed.stderr
    cache = _cache(tmp_path)
    assert build.cached("tf2_msgs", cache) is None
    assert [p.name for p in cache.glob(".tf2_msgs.*.tmp")], list(cache.iterdir())  # what the crash left
    (cache / "tf2_msgs" / "lib").mkdir(parents=True)  # half a tree, as a pre-issue-46 build could leave

    again = subprocess.run([sys.executable, "-c", RUNNER, "run", "tf2_msgs"], cwd=ROOT, env=_env(tmp_path),
                           capture_output=True, text=True, timeout=120)
    assert again.returncode == 0, again.stdout + again.stderr
    assert "ros interfaces: tf2_msgs built and installed" in again.stdout
    assert build.cached("tf2_msgs", cache) == cache / "tf2_msgs"  # complete: share/tf2_msgs/package.xml
    assert _builds(tmp_path) == ["tf2_msgs"]
    assert not [p for p in cache.iterdir() if p.name.startswith(".")], list(cache.iterdir())
