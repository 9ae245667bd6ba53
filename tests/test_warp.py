"""The warp backend's buffers: an overflow grows them and repeats the period, on Warp's CPU device.

The quadruped lands on its feet in its third period of 10 steps; with deliberately tiny
buffers (one contact per world, two constraint rows) that period overflows them. The run
must then go on exactly as one whose buffers were big enough from the start: Warp's CPU
device is deterministic, so the comparison is bit for bit. Where the buffers may not grow
(here: a memory cap of a few bytes), the worlds freeze with OVERFLOW under the contract's
rule instead.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import re

import numpy as np
import pytest

import batchsim
from batchsim import Status

if importlib.util.find_spec("mujoco_warp") is None and os.environ.get("BATCHSIM_FORCE_BACKENDS") != "1":
    pytest.skip("the warp backend needs mujoco_warp, which is not installed", allow_module_level=True)

NWORLD, SUBSTEPS, PERIODS = 2, 10, 8


def run(**options) -> tuple[batchsim.BatchedSystem, list[dict[str, np.ndarray]], dict]:
    """The quadruped under fixed random efforts, read after every period; also the device
    arrays it handed out before the first step."""
    sim = batchsim.make("quadruped", NWORLD, "warp", device="cpu", **options)
    sim.configure()
    sim.activate()
    arrays = sim.device_arrays()
    sim.command = np.random.default_rng(0).uniform(-0.5, 0.5, sim.command.shape)
    sim.write()
    out = []
    for _ in range(PERIODS):
        sim.step(SUBSTEPS)
        sim.read()
        out.append(
            {
                "state": sim.state.copy(),
                "base_state": sim.base_state.copy(),
                "sensordata": np.concatenate([sim.sensordata[n] for n in sim.sensordata], axis=1),
                "time": sim.time.copy(),
                "status": sim.status.copy(),
            }
        )
    return sim, out, arrays


def test_overflowing_buffers_grow_and_the_period_is_repeated(caplog):
    caplog.set_level(logging.WARNING, logger="batchsim.warp")
    reference, expected, _ = run()  # buffers sized from the CPU rollout: they never overflow here
    assert [r for r in caplog.records if "overflowed" in r.getMessage()] == []
    reference.shutdown()

    sim, got, arrays = run(nconmax=1, njmax=2)
    assert sim.nconmax > 1 and sim.njmax > 2
    for period, (a, b) in enumerate(zip(got, expected, strict=True)):
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=f"period {period}: {key}")
    lines = [r.getMessage() for r in caplog.records if r.name == "batchsim.warp"]
    assert lines, "no growth was logged"
    assert re.fullmatch(
        r"batchsim: warp: contact candidates \(nconmax\) and constraint rows \(njmax\) overflowed in 2 of 2 "
        r"worlds; grew nconmax 1 -> \d+ and njmax 2 -> \d+ per world and repeated the period",
        lines[0],
    ), lines[0]
    for line in lines[1:]:
        assert re.fullmatch(r"batchsim: warp: .* overflowed in \d of 2 worlds; grew .* and repeated the period", line)
    assert "--" not in " ".join(lines)  # the library names options, never the command's flags
    # the arrays handed out before the growth are still the simulation's own
    for name, array in sim.device_arrays().items():
        assert arrays[name] is array, name
    base = sim.spec.floating_base
    np.testing.assert_allclose(arrays["qpos"].numpy()[:, base.qposadr : base.qposadr + 7], sim.base_state[:, :7])
    sim.shutdown()


def test_buffers_that_may_not_grow_freeze_the_worlds_with_overflow(caplog):
    caplog.set_level(logging.WARNING, logger="batchsim.warp")
    sim = batchsim.make("quadruped", NWORLD, "warp", device="cpu", nconmax=1, max_data_bytes=1)
    sim.configure()
    sim.activate()
    sim.write()
    last = None
    for _ in range(PERIODS):
        sim.read()
        before = (sim.state.copy(), sim.time.copy())
        sim.step(SUBSTEPS)
        if sim.status.any() and last is None:
            last = before
    sim.read()
    assert sim.nconmax == 1
    assert np.all(sim.status == Status.OVERFLOW)  # the contact pool is shared: every world
    np.testing.assert_array_equal(sim.state, last[0])  # frozen at what it read before the step
    np.testing.assert_array_equal(sim.time, last[1])
    lines = [r.getMessage() for r in caplog.records if r.name == "batchsim.warp"]
    assert len(lines) == 2, lines  # one per world, under the burst limit
    assert re.match(
        r"batchsim: warp: world 0 overflowed at sim time \d+\.\d{4} s \(contact candidates \(nconmax\); "
        r"growing nconmax to \d+ per world needs \d+\.\d\d GiB, more than max_data_bytes allows "
        r"\(0\.00 GiB\)\); frozen until reset",
        lines[0],
    ), lines[0]
    sim.shutdown()
