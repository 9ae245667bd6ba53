"""The cpu backend against a plain Python loop of mujoco.mj_step, one MjData per world."""

from __future__ import annotations

import subprocess
import sys

import mujoco
import numpy as np
import pytest

import batchsim


@pytest.mark.parametrize("model, nthread", [("arm", 1), ("arm", 2), ("quadruped", 2), ("car", 0)])
def test_identical_to_a_plain_mj_step_loop(model, nthread):
    nworld, nperiod, substeps = 5, 30, 4
    sim = batchsim.make(model, nworld, "cpu", nthread=nthread)
    sim.configure()
    sim.activate()
    m = sim.model
    datas = [mujoco.MjData(m) for _ in range(nworld)]
    for d in datas:
        mujoco.mj_forward(m, d)
    act = [c.actuator_id for c in sim.spec.commands]
    rng = np.random.default_rng(1)
    for _ in range(nperiod):
        command = rng.uniform(-1, 1, sim.command.shape)
        sim.command = command
        sim.write()
        sim.step(substeps)
        sim.read()
        for w, d in enumerate(datas):
            d.ctrl[act] = command[w]
            for _ in range(substeps):
                mujoco.mj_step(m, d)
        qpos = np.stack([d.qpos for d in datas])
        qvel = np.stack([d.qvel for d in datas])
        sensordata = np.stack([d.sensordata for d in datas])
        for j in sim.spec.joints:
            names = sim.export_state_interfaces()
            assert np.array_equal(sim.state[:, names.index(f"{j.name}/position")], qpos[:, j.qposadr])
            assert np.array_equal(sim.state[:, names.index(f"{j.name}/velocity")], qvel[:, j.dofadr])
        for s in sim.spec.sensors:
            assert np.array_equal(sim.sensordata[s.name], sensordata[:, s.adr : s.adr + s.dim])
        assert np.array_equal(sim.time, [d.time for d in datas])


# Every world blows up in its first step: a stiff spring pulls a 1 g link towards springref.
EXPLODING = """
<mujoco model="exploding">
  <option timestep="0.01"/>
  <worldbody>
    <body><joint name="hinge" type="hinge" stiffness="1e8" springref="1"/>
      <geom type="capsule" size=".01" fromto="0 0 0 .1 0 0" mass="1e-3"/></body>
  </worldbody>
</mujoco>
"""


def test_divergences_are_logged_by_world_and_mujoco_keeps_its_log_where_asked(tmp_path):
    """8 worlds diverging in one period: three lines naming a world each, one with the count;
    MuJoCo's own lines go to --log-dir, neither to the console nor to the working directory."""
    model = tmp_path / "exploding.xml"
    model.write_text(EXPLODING)
    logs = tmp_path / "logs"
    out = subprocess.run(
        [sys.executable, "-m", "batchsim.cli", "--worlds", "8", "--model", str(model), "--no-ros"]
        + ["--rtf", "0", "--duration", "0.1", "--quiet", "--backend", "cpu", "--log-dir", str(logs)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    lines = [line for line in out.stderr.splitlines() if line.startswith("batchsim: cpu:")]
    assert len(lines) == 4, out.stderr
    for w, line in enumerate(lines[:3]):
        assert line.startswith(
            f"batchsim: cpu: world {w} diverged at sim time 0.0000 s (Nan, Inf or huge value in QACC at DOF 0)"
        ), line
    assert lines[0].endswith(f"MuJoCo's log: {logs.resolve() / 'MUJOCO_LOG.TXT'}")
    assert lines[3] == (
        "batchsim: cpu: 5 more of 8 worlds diverged in the same period (worlds 3, 4, 5, 6, 7); frozen until reset"
    )
    assert "WARNING" not in out.stderr + out.stdout  # MuJoCo's raw lines stay off the console
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
    mujoco_lines = (logs / "MUJOCO_LOG.TXT").read_text().splitlines()
    assert sum("Nan, Inf or huge value in QACC" in line for line in mujoco_lines) == 8
