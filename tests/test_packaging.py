"""batchsim as a wheel (issue 42): `pip install .` (not -e) gave `ModuleNotFoundError:
batchsim.variation`, pyproject.toml listing its packages by hand and missing two, and the build
printed hundreds of lines of setuptools warnings. Here the wheel is built as pip builds it, from
the checkout's files (tracked, and new ones git does not ignore), without build isolation: the
venv's setuptools and wheel (the dev extra), nothing fetched. .ci/run installs that wheel in a
fresh venv and runs the command from it."""

from __future__ import annotations

import importlib.metadata
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from conftest import need

# over a few seconds each: `make test` runs them, `make quick` leaves them out
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parent.parent
PACKAGE_DIRS = {"batchsim": "batchsim", "ros_bridge": "ros_bridge", "models": "batchsim/models"}  # checkout -> wheel


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> tuple[list[str], str]:
    """(the wheel's file names, what the build printed)."""
    need("wheel", "the dev extra installs it: make install")
    setuptools = importlib.metadata.version("setuptools")
    assert int(setuptools.split(".")[0]) >= 77, f"setuptools {setuptools} cannot build batchsim: the dev extra has >= 77"
    source, out = tmp_path_factory.mktemp("source"), tmp_path_factory.mktemp("wheel")
    listed = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"], cwd=ROOT, capture_output=True, check=True
    ).stdout.decode().split("\0")
    for name in filter(None, listed):  # a copy: the build's build/ and egg-info stay out of the checkout
        if (ROOT / name).is_file():
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, source / name)
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-w", str(out), str(source)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    printed = build.stdout + build.stderr
    assert build.returncode == 0, printed
    (wheel,) = out.glob("batchsim-*.whl")
    return zipfile.ZipFile(wheel).namelist(), printed


def test_the_wheel_holds_every_package_of_the_checkout(built):
    names, _ = built
    packages = sorted(
        (Path(PACKAGE_DIRS[top]) / init.relative_to(ROOT / top)).as_posix()
        for top in PACKAGE_DIRS
        for init in (ROOT / top).rglob("__init__.py")
    )
    assert "batchsim/variation/__init__.py" in packages and "ros_bridge/protocol/__init__.py" in packages
    missing = [p for p in packages if p not in names]
    assert not missing, f"the wheel lacks {missing}"
    assert "batchsim/models/arm.xml" in names and "batchsim/models/arm.yaml" in names
    definitions = [p.relative_to(ROOT).as_posix() for p in (ROOT / "ros_bridge/interfaces/definitions").rglob("*") if p.is_file()]
    assert definitions and not [d for d in definitions if d not in names]  # the ROS interfaces, data
    assert not [n for n in names if "__pycache__" in n]


def test_the_wheel_builds_without_a_setuptools_warning(built):
    _, printed = built
    warnings = [line for line in printed.splitlines() if "warn" in line.lower()]
    assert not warnings, "\n".join(warnings)
