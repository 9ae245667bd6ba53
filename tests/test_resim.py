"""Re-simulation's parts without ROS (batchsim.resim): the inputs' message format, and the re-run
itself against a system stepped in-process with commands, resets and randomized draws, recorded
as the loop's recording records them (ros_bridge/input_recording.py). The user's path, from
`batchsim --record` to `batchsim resim`, is tests/test_resim_ros.py."""

from __future__ import annotations

import numpy as np
import pytest

import batchsim
from batchsim.resim import layout as L
from batchsim.resim.compare import compare
from batchsim.resim.physics import rerun
from batchsim.resim.recorded import JointStates, Start, WorldRecord

RANDOMIZE = {
    "seed": 3,
    "redraw_on_reset": True,
    "fields": [
        {"field": "body_mass", "scale": {"uniform": [0.7, 1.3]}},
        {"field": "dof_damping", "scale": {"uniform": [0.5, 2.0]}},
    ],
    "start_pose": {"add": {"normal": [0.0, 0.1]}},
}


def test_inputs_message_is_a_float64_multi_array_any_reader_decodes():
    from mcap_ros2.decoder import DecoderFactory

    from ros_bridge.worker.schemas import schema_text

    header, rows = np.array([7.0, 0.07, 10.0]), np.random.default_rng(0).normal(size=(3, 5))
    data = L.pack(header, rows)
    h, r = L.unpack(data)
    assert (h == header).all() and (r == rows).all()

    from mcap.records import Schema

    schema = Schema(id=1, name=L.MSG_TYPE, encoding="ros2msg", data=schema_text(L.MSG_TYPE).encode())
    msg = DecoderFactory().decoder_for("cdr", schema)(data)
    assert msg.layout.data_offset == 3 and [d.size for d in msg.layout.dim] == [3, 5]
    assert np.array_equal(np.array(msg.data), np.r_[header, rows.ravel()])
    with pytest.raises(ValueError):
        L.unpack(data[:-8])  # one value short


def _record(nworld: int, periods: int, nstep: int, rng) -> tuple:
    """Step a randomized cpu system as the loop does, with random commands and resets, keeping
    what the recording keeps: each period's inputs after write(), starts, joint positions."""
    sim = batchsim.make("arm", nworld, "cpu", randomize=RANDOMIZE)
    sim.configure()
    sim.activate()
    layout = L.layout_of(sim.model, sim.physics_inputs([0]), sim.world_params([0]))
    worlds = np.arange(nworld)
    need = np.ones(nworld, bool)
    headers, inputs, positions, velocities = [], [], [], []
    starts: dict[int, list[Start]] = {w: [] for w in worlds}
    for k in range(periods):
        sim.read()
        if k and k % 40 == 0:  # a reset of two worlds: fresh draws, a fresh start pose
            chosen = rng.choice(nworld, 2, replace=False)
            sim.reset(chosen)
            need[chosen] = True
        positions.append(sim.qstate()[0][:, :6].copy())  # what the bridge's snapshot takes: after a reset
        velocities.append(sim.qstate()[1][:, :6].copy())
        sim.command[:] = rng.uniform(-1, 1, sim.command.shape)
        sim.write()
        header = np.array([k, k * nstep * sim.dt, nstep])  # the loop's clock: a reset world's own time restarts
        for w in np.flatnonzero(need):
            row = layout.start_row([w], sim.draw_numbers()[[w]], sim.physics_state([w]), sim.world_params([w]))[0]
            world, draw, state, params = layout.split_start(row)
            starts[world].append(Start(k, state, draw, params))
        need[:] = False
        headers.append(header)
        inputs.append(layout.input_row(sim.frozen, sim.physics_inputs(worlds)))
        sim.step(nstep)
    return sim, layout, np.array(headers), np.stack(inputs), starts, np.stack(positions), np.stack(velocities)


def test_a_rerun_of_a_randomized_world_with_resets_and_commands_is_bit_exact():
    rng = np.random.default_rng(1)
    sim, layout, headers, inputs, starts, pos, vel = _record(6, 150, 5, rng)
    assert sum(len(s) for s in starts.values()) > 6, "no world was reset"
    names = [f"joint{i}" for i in range(1, 7)]
    stamps = _stamps(headers[:, 1])
    model = L.load_model(L.model_bytes(sim.model))
    for w in range(6):
        record = WorldRecord(w, f"world_{w}", starts[w], inputs[:, w], JointStates(stamps, names, pos[:, w], vel[:, w]))
        result = compare(model, w, rerun(model, layout, headers, record), headers, record.joint_states, 1e-9)
        assert result.compared == 150 and result.exact, result.line()
        assert np.abs(vel[:, w]).max() > 0.5  # it moved
    # the comparison can fail: world 0's re-run against world 1's recorded states
    record = WorldRecord(0, "world_0", starts[0], inputs[:, 0], JointStates(stamps, names, pos[:, 1], vel[:, 1]))
    result = compare(model, 0, rerun(model, layout, headers, record), headers, record.joint_states, 1e-9)
    assert not result.exact and result.first is not None and result.horizon is not None


def _stamps(times: np.ndarray) -> np.ndarray:
    from ros_bridge.worker.messages import stamp_of

    return np.array([s * 1_000_000_000 + n for s, n in map(stamp_of, times)], np.int64)


def test_physics_state_is_mujocos_whole_state_on_cpu():
    import mujoco

    sim = batchsim.make("arm", 3, "cpu")
    sim.configure()
    sim.activate()
    sim.command[:] = 0.3
    sim.write()
    sim.step(7)
    sim.read()
    state = sim.physics_state([2])
    m = sim.model
    d = mujoco.MjData(m)
    mujoco.mj_setState(m, d, state[0], mujoco.mjtState.mjSTATE_INTEGRATION)
    assert d.time == sim.time[2] and np.array_equal(d.qpos, sim.qstate([2])[0][0])
    assert np.any(d.qacc_warmstart != 0)  # the warm start too: what makes a re-run bit-exact
