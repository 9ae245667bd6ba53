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
from batchsim.stamps import stamp_ns, stamp_of, stamps_ns

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


def _record(sim, periods: int, nstep: int, drive) -> tuple:
    """Step `sim` (configured, active) as the loop does, `drive(k)` before each write() (commands,
    resets: it returns the worlds it reset), keeping what the recording keeps: each period's
    inputs after write(), the (re)starts, and the joint state the bridge's snapshot takes."""
    nworld = sim.nworld
    layout = L.layout_of(sim.model, sim.physics_inputs([0]), sim.world_params([0]), _held(sim), sim.command.shape[1])
    worlds = np.arange(nworld)
    need = np.ones(nworld, bool)
    headers, inputs, positions, velocities, efforts = [], [], [], [], []
    columns = [k for k, n in enumerate(sim.export_state_interfaces()) if n.endswith("/effort")]
    starts: dict[int, list[Start]] = {w: [] for w in worlds}
    for k in range(periods):
        sim.read()
        efforts.append(sim.state[:, columns].copy())  # what the broadcaster shows of the last step
        need[drive(k)] = True
        positions.append(sim.qstate()[0].copy())  # what the bridge's snapshot takes: after a reset
        velocities.append(sim.qstate()[1].copy())
        sim.write()
        header = np.array([k, k * nstep * sim.dt, nstep])  # the loop's clock: a reset world's own time restarts
        for w in np.flatnonzero(need):
            row = layout.start_row([w], sim.draw_numbers()[[w]], [True], sim.physics_state([w]), sim.world_params([w]))[0]
            world, draw, fresh, state, params = layout.split_start(row)
            starts[world].append(Start(k, state, draw, params, fresh))
        need[:] = False
        headers.append(header)
        inputs.append(layout.input_row(sim.frozen, {**sim.physics_inputs(worlds), "command": sim.command.copy()}))
        sim.step(nstep)
    return layout, np.array(headers), np.stack(inputs), starts, np.stack(positions), np.stack(velocities), np.stack(efforts)


def _held(sim) -> tuple[int, int]:
    base = sim.base_velocity
    return (base.qposadr, base.dofadr) if base is not None else (-1, -1)


def _rerun_all(sim, recorded, joints: dict[str, tuple[int, int]]) -> list:
    """Every world re-run against its recorded hinge/slide joints `joints` (name -> (qposadr, dofadr))."""
    layout, headers, inputs, starts, pos, vel, eff = recorded
    model = L.load_model(L.model_bytes(sim.model))
    stamps = _stamps(headers[:, 1])
    names = list(joints)
    qadr, vadr = [a for a, _ in joints.values()], [b for _, b in joints.values()]
    sources = L.effort_sources(sim.spec.state)  # as the recording keeps them
    column = {j: k for k, j in enumerate(sources)}  # eff's columns: the effort state interfaces in order
    out = []
    for w in range(sim.nworld):
        effort = np.stack([eff[:, w, column[n]] for n in names], axis=1)
        states = JointStates(stamps, names, pos[:, w][:, qadr], vel[:, w][:, vadr], effort)
        record = WorldRecord(w, f"world_{w}", starts[w], inputs[:, w], [states])
        out.append(compare(model, w, rerun(model, layout, headers, record, effort=sources), headers, [states], 1e-9))
    return out


def test_a_rerun_of_a_randomized_world_with_resets_and_commands_is_bit_exact():
    rng = np.random.default_rng(1)
    sim = batchsim.make("arm", 6, "cpu", randomize=RANDOMIZE)
    sim.configure()
    sim.activate()

    def drive(k: int) -> np.ndarray:
        chosen = rng.choice(6, 2, replace=False) if k and k % 40 == 0 else np.zeros(0, np.intp)
        if chosen.size:  # a reset of two worlds: fresh draws, a fresh start pose
            sim.reset(chosen)
        sim.command[:] = rng.uniform(-1, 1, sim.command.shape)
        return chosen

    recorded = _record(sim, 150, 5, drive)
    assert sum(len(s) for s in recorded[3].values()) > 6, "no world was reset"
    joints = {f"joint{i}": (i - 1, i - 1) for i in range(1, 7)}
    for result in _rerun_all(sim, recorded, joints):
        assert result.compared == 150 and result.exact, result.line()
        assert result.efforts == 6 * (150 - len(recorded[3][result.world])), result  # but in each start's period
    assert np.abs(recorded[5]).max() > 0.5 and np.abs(recorded[6]).max() > 1.0  # they moved, their servos pushed
    # the comparison can fail: world 0's re-run against world 1's recorded states
    layout, headers, inputs, starts, pos, vel, eff = recorded
    model = L.load_model(L.model_bytes(sim.model))
    states = JointStates(_stamps(headers[:, 1]), list(joints), pos[:, 1, :6], vel[:, 1, :6])
    record = WorldRecord(0, "world_0", starts[0], inputs[:, 0], [states])
    result = compare(model, 0, rerun(model, layout, headers, record), headers, [states], 1e-9)
    assert not result.exact and result.first is not None and result.horizon is not None
    # ... and on effort alone: world 0's own positions and velocities, its efforts changed in one period
    effort = eff[:, 0].copy()
    effort[77, 2] += 1e-9
    states = JointStates(_stamps(headers[:, 1]), list(joints), pos[:, 0, :6], vel[:, 0, :6], effort)
    record = WorldRecord(0, "world_0", starts[0], inputs[:, 0], [states])
    result = compare(model, 0, rerun(model, layout, headers, record, effort=L.effort_sources(sim.spec.state)), headers, [states], 1e-9)
    assert not result.exact and result.horizon is None and result.max_position == result.max_velocity == 0.0
    assert result.first[1:3] == (77, "joint3 (effort)") and "1e-09 (effort)" in result.line(), result.line()


def test_the_plugins_inputs_rerun_bit_exact(tmp_path):
    """A free base held by the BaseVelocityPlugin and pushed by the ExternalWrenchPlugin."""
    from batchsim.plugins.base_velocity import PLUGIN_TYPE as BASE
    from batchsim.plugins.external_wrench import PLUGIN_TYPE as WRENCH
    from batchsim.plugins.external_wrench import ExternalWrench

    path = tmp_path / "base.xml"
    path.write_text(PLUGIN_MODEL)
    plugins = {"base": {"type": BASE, "body": "base"}, "push": {"type": WRENCH}}
    sim = batchsim.make(str(path), 3, "cpu", sensors={"/**": {"ros__parameters": {"mujoco_plugins": plugins}}})
    sim.configure()
    sim.activate()

    def drive(k: int) -> np.ndarray:
        if k == 2:
            sim.set_base_velocity([[0.4, 0.1, 0.3], [0.0, 0.0, 0.0], [-0.2, 0.3, -0.5]])
        if k == 5:
            sim.apply_wrench(ExternalWrench("arm", force=(0, 30.0, 0), duration=0.1), worlds=[1, 2])
        sim.command[:] = 0.8 * np.sin(0.1 * k + np.arange(3))[:, None]
        return np.zeros(0, np.intp)

    recorded = _record(sim, 60, 10, drive)
    assert recorded[0].base_velocity and recorded[0].nbody == sim.model.nbody
    wrench = recorded[0].split_inputs(recorded[2].reshape(-1, recorded[0].input_width))["xfrc_applied"]
    assert np.abs(wrench).max() > 0  # a wrench was recorded
    results = _rerun_all(sim, recorded, {"arm_joint": (7, 6)})
    for result in results:
        assert result.compared == 60 and result.exact, result.line()
    # the free joint too: the held base and the pushed arm moved it, and the re-run follows
    layout, headers, inputs, starts, pos, vel, _ = recorded
    model = L.load_model(L.model_bytes(sim.model))
    record = WorldRecord(2, "world_2", starts[2], inputs[:, 2], [])
    run = rerun(model, layout, headers, record)
    assert np.array_equal(run.qpos, pos[:, 2]) and np.abs(pos[-1, 2, :2] - pos[0, 2, :2]).max() > 0.1


PLUGIN_MODEL = """
<mujoco model="resim_plugins">
  <option timestep="0.002"/>
  <worldbody>
    <geom type="plane" size="5 5 0.1"/>
    <body name="base" pos="0 0 0.2">
      <freejoint name="base_joint"/>
      <geom type="box" size="0.2 0.15 0.05" mass="20"/>
      <body name="arm" pos="0 0 0.06">
        <joint name="arm_joint" type="hinge" axis="0 0 1" damping="5"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.025" mass="2"/>
      </body>
    </body>
  </worldbody>
  <actuator><position name="arm_joint" joint="arm_joint" kp="200"/></actuator>
</mujoco>
"""


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


def _stamps(times: np.ndarray) -> np.ndarray:
    """The stamps the bridge gives `times`, one at a time (batchsim.stamps.stamp_ns)."""
    return np.array([stamp_ns(t) for t in times], np.int64)


def test_a_period_is_matched_to_its_messages_by_the_stamp_the_bridge_gives_it():
    """resim's vectorised stamps (batchsim.stamps.stamps_ns) are the bridge's (stamp_of), to the
    nanosecond, on a loop's accumulated clocks and at the edges of a second and of rounding."""
    clocks = np.cumsum(np.full(20_000, 0.01)), np.cumsum(np.full(5000, 0.002)), np.cumsum(np.full(3000, 1 / 300))
    edges = np.array([0.0, 0.9999999995, 0.9999999994999, 1.0000000005, 2.5e-10, 1.5e-9, 7 - 1e-12, 123456.789012345])
    for times in (*clocks, edges):
        assert np.array_equal(stamps_ns(times), _stamps(times))
    assert stamp_of(0.9999999995) == (1, 0) and stamp_ns(1.25) == 1_250_000_000
