"""Parity: every backend follows the cpu backend's trajectory, within float32 tolerance.

Each model starts from the same initial state on every backend and gets the same command
sequence (a new random command each period of 10 steps); the joint positions read back
must stay within the model's tolerance of cpu's (MuJoCo in float64) for the model's
horizon. Horizons stop where the trajectories stop being comparable, not where a backend
fails:

- arm: no contacts, damped position servos; float32 round-off stays below 1e-6 rad over
  the whole 1 s, so the test runs it all.
- car: rests on two cylinder wheels and a caster. While it settles in the first 10 steps,
  MuJoCo Warp's cylinder-plane contacts (symmetric) and MuJoCo's (slightly asymmetric)
  turn the wheels by up to ~1e-2 rad differently; the offset then stays constant over 2 s.
  That is a contact-generation difference, not drift, so the tolerance is 2e-2 rad.
- quadruped: lands on its feet and stays within 1e-6 rad for 0.8 s; after ~1 s its
  contact-rich stance is chaotic and float32 round-off grows to 1e-2.
- humanoid (MuJoCo Warp's packaged test model): falls freely for 0.5 s (agreement ~3e-5);
  once it hits the floor (~0.6 s) the contacts make it chaotic and the backends part.

Worlds are few (3, as in the contract suite, so compiled MJX programs are shared) and the
models run once per backend in the module.
"""

from __future__ import annotations

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


# model -> (control periods of SUBSTEPS steps, tolerance on joint positions in rad or m)
CASES = {
    "arm": (100, 1e-5),
    "car": (100, 2e-2),
    "quadruped": (40, 1e-4),
    "humanoid": (10, 1e-3),
}
_trajectories: dict[tuple[str, str], np.ndarray] = {}


def trajectory(backend: str, model: str) -> np.ndarray:
    """Joint positions after each period, (periods, NWORLD, njoint), cached per module."""
    key = (backend, model)
    if key not in _trajectories:
        periods, _ = CASES[model]
        sim = batchsim.make(humanoid() if model == "humanoid" else model, NWORLD, backend)
        sim.configure()
        sim.activate()
        positions = [i for i, n in enumerate(sim.export_state_interfaces()) if n.endswith("/position")]
        rng = np.random.default_rng(0)
        out = []
        for _ in range(periods):
            sim.command = rng.uniform(-0.3, 0.3, sim.command.shape)
            sim.write()
            sim.step(SUBSTEPS)
            sim.read()
            assert not sim.status.any(), f"{backend} {model}: status {sim.status}"
            out.append(sim.state[:, positions].copy())
        sim.shutdown()
        _trajectories[key] = np.stack(out)
    return _trajectories[key]


@pytest.mark.parametrize("model", list(CASES))
def test_trajectory_matches_cpu(one_device_backend, model):
    backend = one_device_backend
    if backend == "cpu":
        pytest.skip("cpu is the reference")
    periods, tolerance = CASES[model]
    reference = trajectory("cpu", model)
    ours = trajectory(backend, model)
    error = np.abs(ours - reference).max(axis=(1, 2))
    worst = int(error.argmax())
    assert error.max() < tolerance, (
        f"{backend} {model}: joint positions differ from cpu by {error[worst]:.2e} after "
        f"{(worst + 1) * SUBSTEPS} steps (tolerance {tolerance:g})"
    )
