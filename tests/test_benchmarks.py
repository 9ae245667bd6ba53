"""The benchmark scripts' own plumbing (not their timings): what they write and how they fail."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent


def benchmark(name: str):
    """benchmarks/<name>.py as a module (the scripts import their siblings by bare name)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        spec = importlib.util.spec_from_file_location(f"_benchmark_{name}", ROOT / "benchmarks" / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    return module


@pytest.fixture(scope="module")
def sensors():
    return benchmark("sensors")


def test_sensors_json_has_null_for_no_value(sensors, tmp_path):
    rows = [
        {"kind": "lidar", "contract_fps": float("nan"), "raw_fps": 12.5, "ratio": np.float64("nan")},
        {"rtf_windows": [1.0, float("inf"), np.float32(2.0)], "cores": {"physics": float("nan")}, "n": np.int64(3)},
    ]
    out = tmp_path / "out" / "sensors.json"
    sensors.write_json(out, {"header": "# h", "rows": rows})
    text = out.read_text()
    assert "NaN" not in text and "Infinity" not in text
    back = json.loads(text, parse_constant=lambda token: pytest.fail(f"{token} is not JSON"))
    assert back["rows"][0] == {"kind": "lidar", "contract_fps": None, "raw_fps": 12.5, "ratio": None}
    assert back["rows"][1] == {"rtf_windows": [1.0, None, 2.0], "cores": {"physics": None}, "n": 3}
    assert not any(isinstance(v, float) and math.isnan(v) for v in back["rows"][0].values())
