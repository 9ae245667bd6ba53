"""The benchmark scripts' own plumbing (not their timings): what they write and how they fail."""

from __future__ import annotations

import importlib.util
import json
import math
import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest

# over a few seconds each: `make test` runs them, `make quick` leaves them out
pytestmark = pytest.mark.slow

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


DIES = (
    "import sys; print('count 0.0 0 0 0', flush=True); "
    "sys.stderr.write('Traceback (most recent call last):\\n  ...\\nModuleNotFoundError: No module named \\'mujoco\\'\\n'); "
    "sys.exit(1)"
)


def test_sensors_subscribers_keep_the_callers_pythonpath(sensors, monkeypatch):
    """Where MuJoCo is found through PYTHONPATH, a subscriber started with the checkout alone dies."""
    monkeypatch.setenv("PYTHONPATH", "/opt/wheels")
    assert sensors.subscriber_env()["PYTHONPATH"].split(os.pathsep) == [str(ROOT), "/opt/wheels"]
    monkeypatch.delenv("PYTHONPATH")
    assert sensors.subscriber_env()["PYTHONPATH"] == str(ROOT)


def test_a_dead_helper_is_named_with_its_last_stderr_line(sensors):
    helper = sensors.Helper("subscriber 3 (worlds 6..7)", [sys.executable, "-c", DIES], dict(os.environ))
    assert helper.proc.stdout.readline().startswith("count ")
    helper.proc.wait(timeout=30)
    with pytest.raises(sensors.HelperDied) as e:
        helper.check()
    assert str(e.value) == (
        f"subscriber 3 (worlds 6..7) (pid {helper.proc.pid}) exited with status 1: "
        "ModuleNotFoundError: No module named 'mujoco'"
    )


def test_sensors_ros_stage_fails_loudly_when_its_subscribers_die(sensors, monkeypatch, capsys, tmp_path):
    """Before: `received 0 frames/s` and status 0. Now: status 1 and one line saying which died and why.
    The subscribers here die at once, so no batchsim is started."""
    dies = "import sys; sys.stderr.write(\"ModuleNotFoundError: No module named 'mujoco'\\n\"); sys.exit(1)"
    monkeypatch.setattr(sensors, "subscriber_command", lambda domain, lo, hi: [sys.executable, "-c", dies])
    argv = ["--backends", "cpu", "--no-camera", "--no-lidar", "--ros", "2", "--subscriber-processes", "2"]
    assert sensors.main(argv + ["--json", str(tmp_path / "sensors.json")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert re.fullmatch(
        r"sensors\.py: ROS stage, cpu, 2 worlds: subscriber [01] \(worlds (0\.\.0|1\.\.1)\) \(pid \d+\) "
        r"exited with status 1: ModuleNotFoundError: No module named 'mujoco'",
        err[0],
    ), err[0]
    assert not (tmp_path / "sensors.json").exists()


def test_fleet_published_is_the_workers_count_interpolated_between_their_diagnostics():
    fleet = benchmark("fleet")
    assert fleet.at([(0.0, 0.0), (1.0, 100.0)], 0.25) == 25.0
    assert fleet.at([(0.0, 0.0), (1.0, 100.0)], 1.5) is None
    published = fleet.Published.__new__(fleet.Published)  # its counts without its process
    published.samples = {"world_0": [(0.0, 0.0), (1.0, 100.0)], "world_8": [(0.5, 10.0), (1.5, 30.0)]}
    assert published.total(0.75) == 75.0 + 15.0
    assert math.isnan(published.total(0.25))  # world_8's worker had not reported yet: no figure


def test_fleet_and_ros_stack_headers_name_each_librarys_version():
    """The header of fleet.py and ros_stack.py said `rclpy ?` (rclpy has no __version__)."""
    from importlib import metadata

    header = benchmark("fleet")._versions()
    for name, dist in (("mujoco", "mujoco"), ("numpy", "numpy"), ("rclpy", "ros-jazzy-rclpy")):
        try:
            assert f"{name} {metadata.version(dist)}" in header, header
        except metadata.PackageNotFoundError:  # not installed: left out, never a '?'
            assert f"{name} " not in header, header
    assert "?" not in header, header


def test_a_paced_runs_rtf_leaves_out_what_runs_after_the_loop():
    """timed_run's after-hook (view.py's screenshot, the browser's kill) is not loop time: the
    RTF counted it, and a 3 s run with a screenshot read 0.335."""
    import time as wallclock

    timed_run = benchmark("paced_fleet").timed_run

    class Loop:
        control_rate, sim_time = 100.0, 0.0

        def run_period(self, nstep=None):
            self.sim_time += 0.01

        def run(self):
            for _ in range(20):
                self.run_period()
                wallclock.sleep(0.01)

    figures = timed_run(Loop(), after=lambda: wallclock.sleep(0.5))
    assert figures["periods"] == 20 and 0.5 < figures["rtf"] <= 1.2, figures


# ---------------------------------------------------------------- throughput.py: the same physics

needs_warp = pytest.mark.skipif(
    importlib.util.find_spec("mujoco_warp") is None and os.environ.get("BATCHSIM_FORCE_BACKENDS") != "1",
    reason="the warp backend needs mujoco_warp, which is not installed",
)


@needs_warp
def test_throughput_sees_raw_warp_overflow_its_buffers():
    """raw_warp builds MuJoCo Warp's Data at the contract's buffer sizes and turns the overflow
    warning off: once the falling humanoids make more contacts than nconmax, raw drops them
    silently and steps cheaper physics than the contract, which grows its buffers instead.
    unequal_buffers must say so (benchmarks/raw_loops.py; throughput.py and period_profile.py
    then measure again at the grown size)."""
    raw_loops = benchmark("raw_loops")
    import batchsim

    sim = batchsim.make("humanoid", 2, "warp", nconmax=1)  # raised to the start's 8 contacts
    sim.configure()
    sim.activate()
    u = np.random.default_rng(0).uniform(-0.3, 0.3, sim.command.shape)
    built = (sim.nconmax, sim.njmax)
    raw = raw_loops.raw_warp(sim, u)
    assert raw_loops.unequal_buffers(sim, built, [raw]) is None
    why = None
    for _ in range(60):
        sim.command[:] = u
        sim.write()
        sim.step(raw_loops.NSTEP)
        sim.read()
        raw()
        why = raw_loops.unequal_buffers(sim, built, [raw])
        if why is not None:
            break
    sim.shutdown()
    assert why is not None and ("raw overflowed" in why or "the contract grew" in why), why


@needs_warp
def test_throughput_measures_warp_again_when_the_buffers_differed():
    """A warp measurement whose raw loop overflowed is not reported as is: it is measured again
    from the start with every side at the grown buffers, and the note says why."""
    throughput = benchmark("throughput")
    result = throughput.measure("humanoid", "warp", 2, 0.4, rounds=2, buffers=(1, 117), again=True)
    assert result["note"].startswith("measured again from the start at nconmax "), result["note"]
    assert "NOT THE SAME PHYSICS" not in result["note"], result["note"]


def test_controllers_benchmark_says_what_the_thread_did_in_each_period():
    """controllers.py's worst-period line reads the thread's own clock, its switches and faults,
    the hand-over apart from the update, and the VM's steal: a smoke run on 16 arms."""
    controllers = benchmark("controllers")
    r = controllers.measure("arm", "burst", 16, 0.05)
    n = len(r["controllers"])
    assert n >= 3 * 20 and r["usage"].shape == (n, 4) and r["handover"].shape == (n,)
    assert (r["handover"] <= r["controllers"] + 1e-9).all()
    assert r["handover"][r["arrived"]].min() > 0 and (r["handover"][~r["arrived"]] < 1e-3).all()
    cpu = r["usage"][:, 0]
    assert (cpu > 0).all() and (cpu <= r["physics"] + r["controllers"] + 2e-3).all()  # the thread's own seconds
    assert 0.0 <= r["steal"][0] < 1.0
    # the collector's share of each period, and which generation it reached: a full collection is told
    assert r["gc"].shape == (n, 2) and (r["gc"][:, 0] >= 0).all() and set(r["gc"][:, 1]) <= {-1, 0, 1, 2}


def test_controllers_gc_clock_sees_a_full_collection():
    controllers = benchmark("controllers")
    clock = controllers.GcClock()
    try:
        clock.take()
        import gc

        gc.collect()
        seconds, oldest = clock.take()
        assert oldest == 2 and seconds > 0
        assert clock.take() == (0.0, -1)
    finally:
        clock.close()


def test_jitter_prints_its_one_line(capsys, monkeypatch):
    jitter = benchmark("jitter")
    monkeypatch.setattr(sys, "argv", ["jitter.py", "--seconds", "0.2", "--worlds", "64"])
    jitter.main()
    out = capsys.readouterr().out
    assert re.search(r"repetitions of 64 x 6 spline rows: wall ms median [0-9.]+, p99 .* over 5x the median: \d+", out)


def test_cold_start_fails_loudly_when_its_subscribers_die(monkeypatch, capsys):
    """benchmarks/cold_start.py: a subscriber that dies before batchsim starts is one line and
    status 1, not a run that reports no images; no batchsim is started."""
    cold = benchmark("cold_start")
    dies = "import sys; sys.stderr.write('ImportError: rclpy\\n'); sys.exit(1)"
    monkeypatch.setattr(cold, "subscriber_command", lambda domain, lo, hi: [sys.executable, "-c", dies])
    assert cold.main(["--worlds", "2", "--subscribers", "1", "--keep-cache"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.fullmatch(r"cold_start\.py: subscriber 0 \(pid \d+\) exited with status 1: ImportError: rclpy", err[0]), err
