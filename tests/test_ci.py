"""CI's own script (the README's `make test`) fails a run that collects no test (pytest's status 5),
and no test file skips on a missing package behind BATCHSIM_FORCE_BACKENDS's back."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import need

# over a few seconds each: `make test` runs them, `make quick` leaves them out
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parent.parent


def test_ci_fails_when_no_test_is_collected():
    env = {**os.environ, "PYTEST_ADDOPTS": "--ignore-glob=*/test_*.py"}  # nothing left to collect
    out = subprocess.run(["bash", str(ROOT / ".ci" / "run")], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode != 0, out.stdout + out.stderr
    assert "no test was collected; that is a failure" in out.stderr


def test_no_test_file_uses_importorskip_which_ignores_the_force_flag():
    """`pytest.importorskip` skips even under BATCHSIM_FORCE_BACKENDS=1, so a broken install
    (rclpy, jax, mujoco_warp) would pass CI as a row of skips: tests import an optional package
    through conftest's `need`, which fails instead under the flag."""
    found = []
    for path in sorted((ROOT / "tests").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Call):
                func = node.func
                name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
                if name == "importorskip":
                    found.append(f"tests/{path.name}:{node.lineno}")
    assert not found, f"importorskip ignores BATCHSIM_FORCE_BACKENDS; use conftest.need: {', '.join(found)}"


def test_need_skips_a_missing_package_and_fails_under_the_force_flag(monkeypatch):
    monkeypatch.delenv("BATCHSIM_FORCE_BACKENDS", raising=False)
    with pytest.raises(pytest.skip.Exception, match="no_such_package is not importable"):
        need("no_such_package")
    monkeypatch.setenv("BATCHSIM_FORCE_BACKENDS", "1")
    with pytest.raises(ImportError):
        need("no_such_package")
    assert need("json").dumps([]) == "[]"


# the test files that need rclpy at import: through ros_fleet or at their top
ROS_FILES = sorted(
    path.name
    for path in (ROOT / "tests").glob("test_*.py")
    if re.search(r'^(from ros_fleet import|rclpy = need\("rclpy"\))', path.read_text(), re.M)
)
# test_robots.py's plain tests run without ROS: only its tests over ROS need rclpy (a fixture)
ROBOTS_OVER_ROS = "test_mujoco_ros2_control_style_configuration_drives_the_robot_over_ros"
BROKEN = "No module named 'rclpy._rclpy_pybind11' (faked)"


def test_a_broken_ros_install_fails_the_ros_tests_under_the_force_flag(tmp_path):
    """An rclpy whose extension is missing (a broken install, faked ahead of the real one): every
    ROS test file skips without the flag, and fails with it, as CI runs."""
    assert len(ROS_FILES) >= 6, ROS_FILES
    (tmp_path / "rclpy").mkdir()
    (tmp_path / "rclpy" / "__init__.py").write_text(f"raise ModuleNotFoundError({BROKEN!r})\n")
    command = [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-q", "-rsE"]
    command += ["--continue-on-collection-errors"]
    command += [f"tests/{f}" for f in ROS_FILES] + [f"tests/test_robots.py::{ROBOTS_OVER_ROS}"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(tmp_path), os.environ.get("PYTHONPATH")]))}
    env.pop("BATCHSIM_FORCE_BACKENDS", None)
    env.pop("PYTEST_ADDOPTS", None)
    plain = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert plain.returncode == 0, plain.stdout + plain.stderr
    assert f"rclpy is not importable ({BROKEN})" in plain.stdout
    assert re.search(rf"^{len(ROS_FILES) + 1} skipped in ", plain.stdout, re.M), plain.stdout
    env["BATCHSIM_FORCE_BACKENDS"] = "1"
    forced = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert forced.returncode != 0 and "skipped" not in forced.stdout, forced.stdout + forced.stderr
    for f in ROS_FILES:
        assert f"ERROR collecting tests/{f}" in forced.stdout, (f, forced.stdout)
    assert f"ERROR tests/test_robots.py::{ROBOTS_OVER_ROS}" in forced.stdout


def test_the_code_passes_ruff_check():
    """`make lint` as part of the suite, so CI runs it (ruff comes with the dev extra)."""
    ruff = Path(sys.executable).parent / "ruff"
    assert ruff.exists(), "ruff is not installed beside this interpreter (pip install -e '.[dev]')"
    out = subprocess.run(
        [str(ruff), "check", "batchsim", "ros_bridge", "benchmarks", "tests", "examples"],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert out.returncode == 0, out.stdout + out.stderr
