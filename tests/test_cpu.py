"""The cpu backend against a plain Python loop of mujoco.mj_step, one MjData per world."""

from __future__ import annotations

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
