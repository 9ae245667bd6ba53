"""CI's own script (the README's `make test`) fails a run that collects no test (pytest's status 5)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_ci_fails_when_no_test_is_collected():
    env = {**os.environ, "PYTEST_ADDOPTS": "--ignore-glob=*/test_*.py"}  # nothing left to collect
    out = subprocess.run(["bash", str(ROOT / ".ci" / "run")], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode != 0, out.stdout + out.stderr
    assert "no test was collected; that is a failure" in out.stderr
