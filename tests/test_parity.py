"""Parity: every backend follows the cpu backend's trajectory, on every column read() gives.

Each model starts from the same initial state on every backend and gets the same command
sequence (a new random command each period of 10 steps); after each period every state
column (joint positions, velocities and efforts, every sensor field), the floating base's
pose and twist, and time are compared with cpu's (MuJoCo in float64).

The tolerance of a column is `atol + rtol * range`, where `range` is the largest magnitude
the column reaches in cpu's trajectory (at least FLOOR[kind], so that a column that stays
near zero is not held to round-off of nothing): a relative error, comparable across units
(rad, m/s, N, N m). float32 carries ~6e-8 of relative precision per operation; along a
trajectory round-off grows with the dynamics, so the rtol of each model is set at five to
ten times the largest relative error measured on any column with mjx and with warp (on
JAX's and Warp's CPU devices, 2026-11-21; for joint positions also on an H200, see
benchmarks/RESULTS.md), and stays far below what a wrong column (a sign, a stale value, a
swapped index) produces:

- arm: no contacts, damped position servos; the worst column is the wrist torque (1.2e-5
  of its range, warp), so rtol 1e-4 over the whole 1 s.
- car: rests on two cylinder wheels and a caster. While it settles in the first 10 periods,
  MuJoCo Warp's cylinder-plane contacts (symmetric) and MuJoCo's (slightly asymmetric)
  turn the wheels by up to ~1e-2 rad differently; the offset then stays constant over 2 s.
  That is a contact-generation difference, not drift: the settling periods are not
  compared, positions and the base's pose carry the offset as an absolute tolerance (2e-2
  rad for the wheels, 2e-4 m or rad for the base: 9.4e-3 and 9.4e-5 measured), and every
  rate after it agrees to 2e-3 of its range (mjx's wheel velocity as the caster touches
  down; warp 4e-4): rtol 2e-2.
- quadruped: lands on its feet and stays within 6e-5 of range on every column (the base's
  angular velocity; touch forces 1e-5) for 0.8 s: rtol 5e-4; after ~1 s its contact-rich
  stance is chaotic and float32 round-off grows to 1e-2.
- humanoid (MuJoCo Warp's packaged test model): falls freely for 0.5 s; its feet reach the
  floor in the last periods, where mjx's hip velocity parts by 2.3e-4 of its range (warp
  3e-5), and on an H200 the joints parted by 2.3e-4 rad; once it lies on the floor (~0.6 s)
  the contacts make it chaotic and the backends part. rtol 3e-3.

Time is float64 on every backend and is compared exactly. Worlds are few (3, as in the
contract suite, so compiled MJX programs are shared) and the models run once per backend in
the module.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import batchsim

NWORLD, SUBSTEPS = 3, 10


def humanoid() -> str:
    """MuJoCo Warp's packaged humanoid when it is installed, else batchsim's verbatim copy."""
    try:
        import mujoco_warp
    except ImportError:
        return "humanoid"
    return str(Path(mujoco_warp.__file__).parent / "test_data" / "humanoid" / "humanoid.xml")


@dataclasses.dataclass(frozen=True)
class Case:
    """One model's horizon and tolerances: |backend - cpu| <= atol[kind] + rtol[kind] * range."""

    periods: int
    rtol: float
    settle: int = 0  # periods not compared at the start (contacts settling differently)
    atol: dict[str, float] = dataclasses.field(default_factory=dict)  # by kind, default 0


CASES = {
    "arm": Case(100, rtol=1e-4),
    "car": Case(100, rtol=2e-2, settle=10, atol={"position": 2e-2, "base_pose": 2e-4}),
    "quadruped": Case(40, rtol=5e-4),
    "humanoid": Case(10, rtol=3e-3),
}
# below these magnitudes a column's range is round-off, not signal (SI units)
FLOOR = {
    "position": 1e-2,
    "velocity": 1e-2,
    "effort": 1e-2,
    "sensor": 1e-2,
    "base_pose": 1e-2,
    "base_twist": 1e-2,
    "time": 0.0,
}
BASE = ("x", "y", "z", "qw", "qx", "qy", "qz", "vx", "vy", "vz", "wx", "wy", "wz")
_trajectories: dict[tuple[str, str], tuple[list[str], np.ndarray]] = {}


def kind(column: str) -> str:
    """What a column measures, for its tolerance."""
    if column == "time":
        return "time"
    if column.startswith("base/"):
        return "base_pose" if BASE.index(column[5:]) < 7 else "base_twist"
    for interface in ("position", "velocity", "effort"):
        if column.endswith("/" + interface):
            return interface
    return "sensor"


def trajectory(backend: str, model: str) -> tuple[list[str], np.ndarray]:
    """Column names and every column after each period, (periods, NWORLD, ncolumn), cached."""
    key = (backend, model)
    if key not in _trajectories:
        sim = batchsim.make(humanoid() if model == "humanoid" else model, NWORLD, backend)
        sim.configure()
        sim.activate()
        names = sim.export_state_interfaces() + [f"base/{b}" for b in BASE if sim.base_state is not None] + ["time"]
        rng = np.random.default_rng(0)
        out = []
        for _ in range(CASES[model].periods):
            sim.command = rng.uniform(-0.3, 0.3, sim.command.shape)
            sim.write()
            sim.step(SUBSTEPS)
            sim.read()
            assert not sim.status.any(), f"{backend} {model}: status {sim.status}"
            row = [sim.state] + ([sim.base_state] if sim.base_state is not None else []) + [sim.time[:, None]]
            out.append(np.concatenate(row, axis=1))
        sim.shutdown()
        _trajectories[key] = (names, np.stack(out))
    return _trajectories[key]


@pytest.mark.parametrize("model", list(CASES))
def test_trajectory_matches_cpu(one_device_backend, model):
    backend = one_device_backend
    if backend == "cpu":
        pytest.skip("cpu is the reference")
    case = CASES[model]
    names, reference = trajectory("cpu", model)
    assert trajectory(backend, model)[0] == names
    ours = trajectory(backend, model)[1][case.settle :]
    reference = reference[case.settle :]
    kinds = [kind(n) for n in names]
    scale = np.maximum(np.abs(reference).max(axis=(0, 1)), [FLOOR[k] for k in kinds])
    rtol = np.array([0.0 if k == "time" else case.rtol for k in kinds])
    tolerance = np.array([case.atol.get(k, 0.0) for k in kinds]) + rtol * scale
    error = np.abs(ours - reference).max(axis=1)  # (periods, ncolumn)
    over = error > tolerance
    worst = np.where(over, error / np.maximum(tolerance, 1e-300), 0.0)
    period, column = np.unravel_index(int(worst.argmax()), worst.shape)
    assert not over.any(), (
        f"{backend} {model}: {names[column]} differs from cpu by {error[period, column]:.2e} after "
        f"{(period + case.settle + 1) * SUBSTEPS} steps (tolerance {tolerance[column]:.2e}: "
        f"{case.atol.get(kinds[column], 0.0):g} + {rtol[column]:g} x range {scale[column]:.3g})"
    )
