"""The contract suite: every backend must pass it unchanged.

It checks the ros2_control lifecycle table, interface names for each shipped model,
shapes and dtypes, that write() does nothing unless ACTIVE, that reset touches only the
listed worlds, determinism, float64 time, bad input (wrong-shaped and NaN commands, world
lists), and the one rule for a world that fails: frozen at the readings from before the
failing step, logged once by name.
"""

from __future__ import annotations

import dataclasses
import logging
import re

import numpy as np
import pytest
from arrays import host

import batchsim
from batchsim import CallbackReturn, LifecycleError, LifecycleState, ReturnType, Status

S = LifecycleState
NWORLD = 4


def active(model: str, backend: str, nworld: int = NWORLD, **options) -> batchsim.BatchedSystem:
    sim = batchsim.make(model, nworld, backend, **options)
    assert sim.configure() is S.INACTIVE
    assert sim.activate() is S.ACTIVE
    return sim


@pytest.fixture(scope="module")
def arm(backend):
    """One active arm fleet per backend, shared: tests reset the worlds they dirty."""
    sim = active("arm", backend)
    yield sim
    sim.shutdown()


# ---------------------------------------------------------------- the Contract


def test_every_backend_is_a_contract(backend):
    """make() gives a batchsim.Contract on every backend: BatchedSystem over one engine, or a
    fleet over devices composed of one per device, never a subclass that switches features off."""
    sim = batchsim.make("arm", 2, backend)
    assert isinstance(sim, batchsim.Contract)
    sharded = isinstance(sim, batchsim.backends.sharded.ShardedSystem)  # mjx-2dev, warp-2proc: the composite
    assert isinstance(sim, batchsim.BatchedSystem) != sharded
    sim.shutdown()


# ---------------------------------------------------------------- lifecycle


def test_lifecycle_happy_path(backend):
    sim = batchsim.make("arm", 2, backend)
    assert sim.lifecycle_state is S.UNCONFIGURED
    assert sim.configure() is S.INACTIVE
    assert sim.activate() is S.ACTIVE
    assert sim.deactivate() is S.INACTIVE
    assert sim.activate() is S.ACTIVE
    assert sim.deactivate() is S.INACTIVE
    assert sim.cleanup() is S.UNCONFIGURED
    assert sim.configure() is S.INACTIVE
    assert sim.shutdown() is S.FINALIZED


@pytest.mark.parametrize(
    "path, transition",
    [
        ([], "activate"),
        ([], "deactivate"),
        ([], "cleanup"),
        (["configure"], "configure"),
        (["configure"], "deactivate"),
        (["configure", "activate"], "activate"),
        (["configure", "activate"], "cleanup"),
        (["shutdown"], "configure"),
        (["shutdown"], "shutdown"),
    ],
)
def test_illegal_transitions_name_the_state(backend, path, transition):
    sim = batchsim.make("arm", 1, backend)
    for t in path:
        getattr(sim, t)()
    state = sim.lifecycle_state
    with pytest.raises(LifecycleError, match=f"the system is {state.name}"):
        getattr(sim, transition)()
    assert sim.lifecycle_state is state


class _Scripted(batchsim.SystemInterface):
    """A lifecycle whose callbacks return what the test says."""

    def __init__(self, **results):
        super().__init__()
        self.results = results
        self.calls = []

    def __getattribute__(self, name):
        if name.startswith("on_") and name in object.__getattribute__(self, "results"):
            result = object.__getattribute__(self, "results")[name]

            def callback(*args):
                object.__getattribute__(self, "calls").append(name)
                return result

            return callback
        return object.__getattribute__(self, name)


F, E, OK = CallbackReturn.FAILURE, CallbackReturn.ERROR, CallbackReturn.SUCCESS


@pytest.mark.parametrize(
    "results, path, expected",
    [
        # ros2_control's hardware_interface::System table, outcome by outcome
        ({"on_init": F}, ["initialize"], S.FINALIZED),
        ({"on_init": E}, ["initialize"], S.FINALIZED),
        ({"on_configure": F}, ["initialize", "configure"], S.UNCONFIGURED),
        ({"on_configure": E, "on_error": OK}, ["initialize", "configure"], S.UNCONFIGURED),
        ({"on_configure": E, "on_error": F}, ["initialize", "configure"], S.FINALIZED),
        ({"on_activate": F}, ["initialize", "configure", "activate"], S.INACTIVE),
        ({"on_activate": E}, ["initialize", "configure", "activate"], S.UNCONFIGURED),
        ({"on_deactivate": F}, ["initialize", "configure", "activate", "deactivate"], S.ACTIVE),
        ({"on_deactivate": E}, ["initialize", "configure", "activate", "deactivate"], S.UNCONFIGURED),
        ({"on_cleanup": F}, ["initialize", "configure", "cleanup"], S.UNCONFIGURED),
        ({"on_cleanup": F, "on_error": E}, ["initialize", "configure", "cleanup"], S.FINALIZED),
        ({"on_shutdown": F}, ["initialize", "configure", "shutdown"], S.UNCONFIGURED),
        ({"on_shutdown": OK}, ["initialize", "configure", "activate", "shutdown"], S.FINALIZED),
    ],
)
def test_transition_table(results, path, expected):
    system = _Scripted(**results)
    for t in path:
        getattr(system, t)()
    assert system.lifecycle_state is expected


def test_callback_exception_runs_on_error_then_propagates():
    class Broken(batchsim.SystemInterface):
        def on_configure(self, previous_state):
            raise RuntimeError("no device")

    system = Broken()
    system.initialize()
    with pytest.raises(RuntimeError, match="no device"):
        system.configure()
    assert system.lifecycle_state is S.UNCONFIGURED


# ---------------------------------------------------------------- interfaces

ARM_JOINTS = [f"joint{i}" for i in range(1, 7)]
QUAD_JOINTS = [f"{leg}_{j}" for leg in ("FL", "FR", "HL", "HR") for j in ("hip_abduction", "hip_flexion", "knee")]


@pytest.mark.parametrize(
    "model, commands, some_states",
    [
        (
            "arm",
            [f"{j}/position" for j in ARM_JOINTS],
            ["joint1/position", "joint1/velocity", "joint1/effort", "wrist_force/force.x", "wrist_torque/torque.z"],
        ),
        (
            "car",
            ["left_wheel_joint/effort", "right_wheel_joint/effort"],
            ["left_wheel_joint/velocity", "left_wheel_torque/effort"],
        ),
        (
            "quadruped",
            [f"{j}/effort" for j in QUAD_JOINTS],
            [
                "FL_knee/position",
                "imu_orientation/orientation.w",
                "imu_gyro/angular_velocity.x",
                "imu_accel/linear_acceleration.z",
                "HR_foot_touch/force",
            ],
        ),
    ],
)
def test_interface_names(backend, model, commands, some_states):
    sim = batchsim.make(model, 2, backend)
    assert sim.export_command_interfaces() == commands
    states = sim.export_state_interfaces()
    assert len(states) == len(set(states))
    for name in some_states:
        assert name in states
    joints = {s.split("/")[0] for s in states if s.endswith(("/position", "/velocity", "/effort"))}
    for c in commands:
        joint = c.split("/")[0]
        assert f"{joint}/position" in states and f"{joint}/velocity" in states and f"{joint}/effort" in states
        assert joint in joints


def test_shapes_and_dtypes(arm):
    n, nstate, ncmd = NWORLD, len(arm.export_state_interfaces()), len(arm.export_command_interfaces())
    assert arm.state.shape == (n, nstate) and arm.state.dtype == np.float64
    assert arm.command.shape == (n, ncmd) and arm.command.dtype == np.float64
    assert arm.status.shape == (n,)
    assert arm.time.shape == (n,) and arm.time.dtype == np.float64
    assert set(arm.sensordata) == {s.name for s in arm.spec.sensors}
    assert arm.sensordata["wrist_force"].shape == (n, 3)
    assert arm.sensordata["joint1_pos"].shape == (n, 1)
    assert arm.read() is ReturnType.OK and arm.write() is ReturnType.OK


def test_state_columns_follow_the_simulation(arm):
    arm.reset()
    arm.command[:, 0] = 0.4
    for _ in range(50):
        arm.write()
        arm.step(10)
    arm.read()
    names = arm.export_state_interfaces()
    pos = arm.state[:, names.index("joint1/position")]
    assert np.allclose(pos, 0.4, atol=0.02)
    # the jointpos sensor is one substep behind the state, as with mj_step
    assert np.allclose(arm.sensordata["joint1_pos"][:, 0], pos, atol=1e-3)
    assert np.allclose(arm.time, 0.5, atol=1e-9)
    # gravity on the tool: the wrist force sensor sees its weight
    assert np.all(np.abs(arm.sensordata["wrist_force"]).max(axis=1) > 1.0)
    arm.reset()


def test_device_arrays_show_what_write_and_read_show(arm):
    """device_arrays() is the same simulation as read(): ctrl as last written, qpos as read."""
    arm.reset()
    arm.command[:] = np.linspace(-0.2, 0.2, NWORLD)[:, None]
    arm.write()
    arrays = arm.device_arrays()
    ctrl = host(arrays["ctrl"])  # position servos: ctrl is the command, column for column
    assert np.allclose(ctrl[:, arm.ctrl_index], arm.command, atol=1e-6)
    arm.step(10)
    arm.read()
    arrays = arm.device_arrays()  # step() may have replaced them (mjx donates its buffers)
    names = arm.export_state_interfaces()
    pos = arm.state[:, [names.index(f"joint{i}/position") for i in range(1, 7)]]
    assert np.allclose(host(arrays["qpos"]), pos, atol=1e-6)
    assert np.allclose(host(arrays["time"]), arm.time, atol=1e-6)
    arm.reset()


def on_device(sim: batchsim.BatchedSystem, values: np.ndarray):
    """`values` as an array on `sim`'s engine device, of the engine's own kind (write_device)."""
    ctrl = sim.device_arrays()["ctrl"]
    if isinstance(ctrl, np.ndarray):
        return values
    if type(ctrl).__module__.startswith("warp"):
        import warp as wp

        return wp.array(values, dtype=wp.float32, device=ctrl.device)
    import jax

    return jax.device_put(values, next(iter(ctrl.devices())))


def test_a_reset_keeps_the_other_worlds_device_written_commands(one_device_backend):
    """write_device() after write(), then a reset of one world: the others keep what
    write_device() wrote (warp uploaded its host copy of ctrl, from the last write())."""
    sim = active("arm", one_device_backend)
    try:
        sim.command[:] = 0.1
        sim.write()
        sim.write_device(on_device(sim, np.full(sim.command.shape, 0.25, np.float32)))
        sim.reset(worlds=[0])
        ctrl = host(sim.device_arrays()["ctrl"])[:, sim.ctrl_index]
        assert np.allclose(ctrl[1:], 0.25, atol=1e-6), ctrl
    finally:
        sim.shutdown()


# ---------------------------------------------------------------- write / read gating


def test_write_is_ignored_unless_active(backend):
    sim = batchsim.make("arm", 2, backend)
    sim.command[:] = 1.0
    assert sim.write() is ReturnType.OK  # UNCONFIGURED: nothing to write to
    sim.configure()
    sim.command[:] = 1.0
    assert sim.write() is ReturnType.OK  # INACTIVE: ignored
    sim.step(100)
    sim.read()
    pos = sim.state[:, sim.export_state_interfaces().index("joint1/position")]
    assert np.allclose(pos, 0.0, atol=1e-3)
    sim.activate()
    sim.command[:] = 0.3
    sim.write()
    sim.step(300)
    sim.read()
    pos = sim.state[:, sim.export_state_interfaces().index("joint1/position")]
    assert np.all(np.abs(pos - 0.3) < 0.05)
    sim.shutdown()


def test_a_backend_says_whether_its_first_period_compiles(backend):
    """A capability of the class, not a name the command line checks (issue 22): a fleet over
    several devices says what its shards' class says (tests/test_model.py checks the shipped ones)."""
    sim = batchsim.make("arm", 2, backend)
    stated = batchsim.backends.backend_class(batchsim.backends.parse(backend)).compiles_first_period
    assert isinstance(stated, bool)
    assert sim.compiles_first_period is stated


def test_step_needs_a_configured_system(backend):
    sim = batchsim.make("arm", 1, backend)
    with pytest.raises(LifecycleError, match="UNCONFIGURED"):
        sim.step(1)


@pytest.mark.parametrize("nstep", [2.5, 0, -1, True, "3"])
def test_step_takes_a_whole_number_of_steps(arm, nstep):
    """Issue 23: step(2.5) ran 2 steps; every backend refuses what is not a whole count >= 1."""
    with pytest.raises(ValueError, match="nstep must be a whole number of physics steps >= 1"):
        arm.step(nstep)
    arm.step(np.int64(1))  # NumPy's integers are whole numbers too


def test_write_while_unconfigured_does_nothing_as_ros2_control_does():
    """ros2_control (jazzy's hardware_interface/system.cpp) skips read() and write() with OK in
    UNKNOWN, UNCONFIGURED and FINALIZED (lifecycleStateThatRequiresNoAction); so does the contract."""
    sim = batchsim.make("arm", 1, "cpu")
    assert sim.write() is ReturnType.OK and sim.read() is ReturnType.OK


def test_read_and_write_say_ok_outside_inactive_and_active_on_every_backend(backend):
    """Issue 42 asked for ERROR from write() while UNCONFIGURED; ros2_control has answered OK
    there since ros2_control#1279 (System::read and ::write, lifecycleStateThatRequiresNoAction;
    jazzy's HardwareComponent alike): OK, doing nothing, in UNKNOWN, UNCONFIGURED and FINALIZED,
    ERROR only in a transition state, which the contract has none of. Every backend, a fleet
    over several devices too (its shards gone once FINALIZED), answers so."""
    sim = batchsim.make("arm", 2, backend)
    assert sim.write() is ReturnType.OK and sim.read() is ReturnType.OK  # UNCONFIGURED
    sim.configure()
    assert sim.write() is ReturnType.OK and sim.read() is ReturnType.OK  # INACTIVE: read, nothing written
    assert sim.shutdown() is S.FINALIZED
    assert sim.write() is ReturnType.OK and sim.read() is ReturnType.OK


# ---------------------------------------------------------------- reset


def test_reset_touches_only_listed_worlds(arm):
    arm.reset()
    arm.command[:] = np.linspace(0.1, 0.4, NWORLD)[:, None]
    for _ in range(20):
        arm.write()
        arm.step(10)
    arm.read()
    before = arm.state.copy()
    time_before = arm.time.copy()
    arm.reset(worlds=[1, 3])
    after = arm.state
    assert np.array_equal(after[[0, 2]], before[[0, 2]])
    assert np.array_equal(arm.time[[0, 2]], time_before[[0, 2]])
    assert np.allclose(arm.time[[1, 3]], 0.0)
    names = arm.export_state_interfaces()
    assert np.allclose(after[[1, 3], names.index("joint1/position")], 0.0)
    # the reset worlds' commands go back to holding the initial pose
    assert np.allclose(arm.command[[1, 3]], 0.0)
    assert np.allclose(arm.command[[0, 2], 0], [0.1, 0.3])
    arm.reset()


def test_reset_takes_the_worlds_in_any_order(arm):
    """reset([3, 1]) resets worlds 1 and 3, as reset([1, 3]) does: the contract takes worlds in
    any order (cpu's mujoco.batch wants its ids ascending, and raised for these; found by a
    review). Only those two worlds change, and each goes back to the initial state."""
    arm.reset()
    initial = arm.state.copy()
    arm.command[:] = np.linspace(0.1, 0.4, NWORLD)[:, None]
    for _ in range(20):
        arm.write()
        arm.step(10)
    arm.read()
    before, time_before = arm.state.copy(), arm.time.copy()
    assert not np.allclose(before[[1, 3]], initial[[1, 3]])
    arm.reset([3, 1])
    np.testing.assert_array_equal(arm.state[[0, 2]], before[[0, 2]])
    np.testing.assert_array_equal(arm.time[[0, 2]], time_before[[0, 2]])
    np.testing.assert_allclose(arm.state[[1, 3]], initial[[1, 3]], atol=1e-9)
    np.testing.assert_allclose(arm.time[[1, 3]], 0.0)
    assert np.allclose(arm.command[[1, 3]], 0.0) and np.allclose(arm.command[[0, 2], 0], [0.1, 0.3])
    arm.reset()


def test_set_qstate_teleports_only_the_listed_worlds(arm):
    """qstate/set_qstate (mujoco_ros2_control's reset_world overrides and set_free_joint_state):
    whole qpos/qvel rows in the caller's order; state shows them at once; nothing else moves."""
    arm.reset()
    arm.read()
    m = arm.model
    qpos, qvel = arm.qstate()
    assert qpos.shape == (NWORLD, m.nq) and qvel.shape == (NWORLD, m.nv) and qpos.dtype == np.float64
    before = arm.state.copy()
    rows = np.array([np.full(m.nq, 0.3), np.full(m.nq, -0.2)])
    arm.set_qstate([3, 1], rows, np.zeros((2, m.nv)))
    position = [arm.export_state_interfaces().index(f"joint{j}/position") for j in range(1, 7)]
    np.testing.assert_allclose(arm.state[3, position], 0.3, atol=1e-6)
    np.testing.assert_allclose(arm.state[1, position], -0.2, atol=1e-6)
    np.testing.assert_array_equal(arm.state[[0, 2]], before[[0, 2]])
    np.testing.assert_allclose(arm.qstate([1, 3])[0], rows[::-1], atol=1e-6)
    arm.write()
    arm.step(1)  # the engine goes on from there
    arm.read()
    assert abs(arm.state[3, position[0]] - 0.3) < 0.05
    with pytest.raises(ValueError, match=r"qpos must have shape \(1, 6\), got \(6,\)"):
        arm.set_qstate([0], np.zeros(m.nq), np.zeros((1, m.nv)))
    with pytest.raises(ValueError, match="qvel holds NaN"):
        arm.set_qstate([0], np.zeros((1, m.nq)), np.full((1, m.nv), np.nan))
    arm.reset()


def test_reset_rejects_unknown_worlds(arm):
    with pytest.raises(ValueError, match="world 4 is out of range"):
        arm.reset(worlds=[4])
    with pytest.raises(ValueError, match="world -1 is out of range"):
        arm.reset(worlds=[2, -1])


# ---------------------------------------------------------------- world lists


def test_set_command_rows_follow_the_order_given(arm):
    """Row i goes to worlds[i], whatever the order; the other worlds keep theirs."""
    arm.reset()
    ncmd = arm.command.shape[1]
    rows = np.array([np.full(ncmd, 0.1), np.full(ncmd, 0.3)])
    arm.set_command(rows, worlds=[3, 1])
    np.testing.assert_array_equal(arm.command[3], rows[0])
    np.testing.assert_array_equal(arm.command[1], rows[1])
    np.testing.assert_array_equal(arm.command[[0, 2]], 0.0)
    arm.set_command(rows, worlds=np.array([True, False, True, False]))  # a mask: in world order
    np.testing.assert_array_equal(arm.command[[0, 2]], rows)
    arm.reset()


def test_a_world_listed_twice_is_an_error(arm):
    ncmd = arm.command.shape[1]
    before = arm.command.copy()
    with pytest.raises(ValueError, match="world 1 is listed more than once"):
        arm.set_command(np.zeros((3, ncmd)), worlds=[1, 2, 1])
    with pytest.raises(ValueError, match="world 3 is listed more than once"):
        arm.reset(worlds=[3, 3])
    with pytest.raises(ValueError, match="must be integers"):
        arm.set_command(np.zeros((1, ncmd)), worlds=[1.5])
    np.testing.assert_array_equal(arm.command, before)


def test_worlds_index_is_the_one_reading_of_a_world_list():
    """batchsim.types.worlds_index: what the contract's `worlds=`, SimLoop.reset and
    switch_controller take, with one set of checks and messages (issue 42)."""
    from batchsim.types import worlds_index

    assert worlds_index(None, 4) is None
    np.testing.assert_array_equal(worlds_index([3, 1], 4), [3, 1])  # the caller's order
    np.testing.assert_array_equal(worlds_index(np.array([True, False, True, False]), 4), [0, 2])
    np.testing.assert_array_equal(worlds_index(2, 4), [2])
    assert worlds_index([], 4).dtype == np.int64 and worlds_index([], 4).size == 0
    for worlds, message in [
        ([4], "^world 4 is out of range: worlds are 0..3$"),
        ([1, 2, 1], "^world 1 is listed more than once$"),
        (np.array([True, False]), r"^a world mask must have shape \(4,\), got \(2,\)$"),
        ([1.5], r"^worlds must be integers or a \(4,\) bool mask, got float64$"),
    ]:
        with pytest.raises(ValueError, match=message):
            worlds_index(worlds, 4)
    with pytest.raises(ValueError, match="^jtc: world -1 is out of range"):
        worlds_index([-1], 4, what="jtc")


# ---------------------------------------------------------------- determinism


def _rollout(backend: str, model: str, nworld: int, nperiod: int) -> np.ndarray:
    # deterministic=True: on a GPU, mjx and warp sum with atomics in varying order unless
    # asked not to (the two runs then agree only to float32 rounding; seen on an H200)
    sim = active(model, backend, nworld, deterministic=True)
    rng = np.random.default_rng(0)
    ncmd = len(sim.export_command_interfaces())
    out = []
    for _ in range(nperiod):
        sim.command = rng.uniform(-0.5, 0.5, (nworld, ncmd))
        sim.write()
        sim.step(5)
        sim.read()
        out.append(sim.state.copy())
    sim.shutdown()
    return np.stack(out)


@pytest.mark.parametrize("model", ["arm", "quadruped"])
def test_determinism(backend, model):
    a = _rollout(backend, model, 3, 20)
    b = _rollout(backend, model, 3, 20)
    assert np.array_equal(a, b)
    assert np.isfinite(a).all()


# ---------------------------------------------------------------- bad input


def test_wrong_shape_command_raises_naming_shapes(arm):
    ncmd = len(arm.export_command_interfaces())
    with pytest.raises(ValueError, match=rf"\({NWORLD}, {ncmd}\).*got \({NWORLD}, {ncmd + 1}\)"):
        arm.command = np.zeros((NWORLD, ncmd + 1))
    with pytest.raises(ValueError, match=rf"got \({ncmd - 1},\)"):
        arm.set_command(np.zeros(ncmd - 1))
    assert arm.command.shape == (NWORLD, ncmd)


def test_nan_command_sets_bad_command_and_spares_the_others(arm):
    arm.reset()
    arm.command[:] = 0.2
    arm.write()
    arm.step(50)
    # world 2 gets a NaN: not applied, BAD_COMMAND; world 1 gets 0.2 again, as a twin of what
    # world 2 must do (hold its last good command); worlds 0 and 3 take 0.25
    arm.command[:] = 0.25
    arm.command[1] = 0.2
    arm.command[2, 3] = np.nan
    assert arm.write() is ReturnType.OK
    assert arm.status[2] & Status.BAD_COMMAND
    assert not np.any(arm.status[[0, 1, 3]] & Status.BAD_COMMAND)
    arm.step(200)
    arm.read()
    names = arm.export_state_interfaces()
    j1 = names.index("joint1/position")
    # world 2 followed its twin: the same commands from the same state, so the same readings
    # (float32 round-off on the device backends, which compute each world alike)
    np.testing.assert_allclose(arm.state[2], arm.state[1], rtol=0, atol=1e-6)
    np.testing.assert_allclose(arm.sensordata["wrist_force"][2], arm.sensordata["wrist_force"][1], rtol=0, atol=1e-5)
    assert abs(arm.state[2, j1] - 0.2) < 0.02
    assert np.all(np.abs(arm.state[[0, 3], j1] - 0.25) < 0.02)
    assert np.isfinite(arm.state).all()
    assert not np.any(arm.status & (Status.DIVERGED | Status.OVERFLOW))
    # a good command clears the bit
    arm.command[:] = 0.0
    arm.write()
    assert not np.any(arm.status & Status.BAD_COMMAND)
    arm.reset()


def test_write_takes_the_commands_as_they_are_then(arm):
    """write() applies `command` as it is when called: edits after it wait for the next write(),
    and a reset of some worlds leaves the others' written commands in place (warp's commands
    go up whole and are checked on the device; the host's copy of ctrl lags until a reset or
    a park needs it)."""
    arm.reset()
    j1 = arm.export_state_interfaces().index("joint1/position")
    arm.command[:] = 0.25
    arm.command[1] = 0.2
    arm.write()
    arm.command[:] = np.nan  # not written: never reaches the worlds
    arm.reset(worlds=[0])  # after the write: worlds 1-3 keep theirs; world 0 holds its start
    arm.step(200)
    arm.read()
    assert not np.any(arm.status)
    assert abs(arm.state[1, j1] - 0.2) < 0.02
    assert np.all(np.abs(arm.state[[2, 3], j1] - 0.25) < 0.02)
    assert abs(arm.state[0, j1]) < 0.02
    arm.command[:] = 0.0
    arm.reset()


@pytest.mark.parametrize("value", [np.inf, -np.inf, 1e11])
def test_inf_and_huge_commands_are_rejected_too(arm, value):
    arm.reset()
    arm.command[1, 0] = value
    arm.write()
    assert arm.status[1] & Status.BAD_COMMAND
    arm.reset(worlds=[1])
    assert arm.status[1] == 0


# A floating base carrying a tiny link on an unlimited motor: an absurd but finite torque on
# the link blows the world up in its first step, base included; zero torque keeps it falling.
UNSTABLE = """
<mujoco model="unstable">
  <worldbody>
    <body name="base" pos="0 0 1">
      <freejoint name="root"/>
      <geom type="box" size=".1 .1 .1" mass="1"/>
      <body name="link">
        <joint name="hinge" type="hinge" axis="0 0 1" damping="0"/>
        <geom type="capsule" size=".01" fromto="0 0 0 .1 0 0" mass="1e-3"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor name="motor" joint="hinge"/></actuator>
  <sensor>
    <jointvel name="vel" joint="hinge"/>
    <framepos name="base_pos" objtype="body" objname="base"/>
  </sensor>
</mujoco>
"""
SUBSTEPS, CALM = 5, 4  # steps per period; periods before world 1 gets its torque


def _readings(sim) -> dict[str, np.ndarray]:
    return {
        "state": sim.state.copy(),
        "base_state": sim.base_state.copy(),
        "sensordata": np.concatenate([sim.sensordata[n] for n in sim.sensordata], axis=1),
        "time": sim.time.copy(),
    }


def _blow_up_world_1(sim, read_every_period: bool) -> dict[str, np.ndarray]:
    """CALM calm periods, then world 1's torque; returns the readings just before that step."""
    sim.command[:] = 0.0
    for _ in range(CALM):
        sim.write()
        sim.step(SUBSTEPS)
        if read_every_period:
            sim.read()
    sim.read()
    before = _readings(sim)
    sim.command[1] = 1e9
    sim.write()
    sim.step(SUBSTEPS)
    return before


@pytest.fixture
def unstable(tmp_path):
    path = tmp_path / "unstable.xml"
    path.write_text(UNSTABLE)
    return str(path)


def test_a_diverging_world_is_frozen_at_its_last_readings_and_the_others_go_on(backend, unstable, caplog):
    """One rule on every backend: a failed world reads, until reset, exactly what read() showed
    before the failing step (state, base_state, sensordata, time); the log names it once."""
    caplog.set_level(logging.WARNING, logger="batchsim")
    sim = active(unstable, backend, 3, deterministic=True)
    assert sim.base_state is not None
    before = _blow_up_world_1(sim, read_every_period=True)
    assert sim.status[1] & Status.DIVERGED
    assert not np.any(sim.status[[0, 2]] & Status.DIVERGED)
    dt = sim.dt
    for _ in range(3):  # frozen, however often it is stepped and read
        sim.read()
        for key, value in _readings(sim).items():
            np.testing.assert_array_equal(value[1], before[key][1], err_msg=f"{backend}: frozen {key}")
        assert np.isfinite(sim.state[[0, 2]]).all()
        sim.step(SUBSTEPS)
    sim.read()
    np.testing.assert_array_equal(sim.state[1], before["state"][1])
    # the others went on, one timestep at a time in float64
    expected = before["time"][0]
    for _ in range(4 * SUBSTEPS):
        expected += dt
    np.testing.assert_array_equal(sim.time[[0, 2]], expected)
    assert np.all(sim.base_state[[0, 2], 2] < before["base_state"][[0, 2], 2])  # still falling
    # one line, naming the world, when it froze and why
    lines = [r.getMessage() for r in caplog.records if r.name == f"batchsim.{backend}"]
    assert len(lines) == 1, lines
    assert re.search(
        rf"^batchsim: {backend}: world 1 diverged at sim time {before['time'][1]:.4f} s "
        r"\(Nan, Inf or huge value in Q(POS|VEL|ACC) at DOF \d+\); frozen until reset",
        lines[0],
    ), lines[0]
    # reset brings it back, finite, at its initial state
    sim.reset(worlds=[1])
    assert sim.status[1] == 0
    assert sim.time[1] == 0.0
    np.testing.assert_array_equal(sim.base_state[1, :3], [0, 0, 1])
    sim.command[1] = 0.0
    sim.write()
    sim.step(SUBSTEPS)
    sim.read()
    assert np.isfinite(sim.state).all() and not sim.status.any()
    sim.shutdown()


def test_frozen_readings_do_not_depend_on_reading_between_steps(backend, unstable):
    """A world that fails in a step() that followed another without read() freezes at the same
    readings as when the loop reads every period."""
    frozen = []
    for read_every_period in (True, False):
        sim = active(unstable, backend, 3, deterministic=True)
        before = _blow_up_world_1(sim, read_every_period)
        sim.read()
        assert sim.status[1] & Status.DIVERGED
        frozen.append(_readings(sim))
        for key in frozen[-1]:
            np.testing.assert_array_equal(frozen[-1][key][1], before[key][1])
        sim.shutdown()
    for key in frozen[0]:
        np.testing.assert_array_equal(frozen[0][key], frozen[1][key], err_msg=key)


# UNSTABLE with a force/torque sensor at the hinge (read negated, as mujoco_ros2_control does)
UNSTABLE_FTS = UNSTABLE.replace(
    '<geom type="capsule" size=".01"', '<site name="ft"/><geom type="capsule" size=".01"'
).replace(
    "</sensor>",
    '<force name="ft_force" site="ft"/><torque name="ft_torque" site="ft"/></sensor>'
    '<ros2_control name="u" type="system"><hardware><plugin>mujoco_ros2_control/MujocoSystemInterface</plugin>'
    '</hardware><joint name="hinge"><command_interface name="effort"/><state_interface name="position"/>'
    '<state_interface name="velocity"/></joint>'
    '<sensor name="ft"><param name="mujoco_type">fts</param></sensor></ros2_control>',
)
NOISY = {"sensors": {"seed": 3, "noise": {"hinge/*": {"stddev": 0.01}, "ft/*": {"stddev": 0.01}}}}


def test_frozen_readings_are_signed_and_noise_free(backend, tmp_path):
    """A failed world holds its noise-free readings with the force/torque columns negated as
    read() gives them, whether the loop read just before the failing step or not (an engine
    gather then), and gets no fresh noise while frozen."""
    path = tmp_path / "unstable_fts.xml"
    path.write_text(UNSTABLE_FTS)
    for read_before in (True, False):
        sim = active(str(path), backend, 3, deterministic=True, sensors=NOISY)
        torque_z = sim.export_state_interfaces().index("ft/torque.z")
        sim.command[:] = 1e-3  # a small torque: the sensor reads something, of one sign
        for _ in range(CALM):
            sim.write()
            sim.step(SUBSTEPS)
        if read_before:
            sim.read()
            truth = sim.true_state.copy()
            if sim.reads_torque_sensors:  # MJX's torque sensor reads 0 here (its cfrc_int): no sign to see
                assert abs(truth[1, torque_z]) > 1e-5
            assert not np.array_equal(sim.state, truth)  # the noise is on
        sim.command[1] = 1e9
        sim.write()
        sim.step(SUBSTEPS)
        assert sim.status[1] & Status.DIVERGED
        for _ in range(3):  # the same, noise-free readings on every read, signed as before
            sim.read()
            np.testing.assert_array_equal(sim.state[1], truth[1], err_msg=f"{backend} read before: {read_before}")
            np.testing.assert_array_equal(sim.true_state[1], truth[1])
            assert not np.array_equal(sim.state[[0, 2]], sim.true_state[[0, 2]])  # the others stay noisy
            sim.step(SUBSTEPS)
        sim.shutdown()


# ---------------------------------------------------------------- time


def test_time_is_float64_far_from_zero(backend):
    """Past 32768 s a float32 clock no longer moves by a 1 ms step; sim.time must, as cpu's."""
    spec = batchsim.load("arm")
    spec = dataclasses.replace(spec, initial=dataclasses.replace(spec.initial, time=40000.0))
    sim = batchsim.make(spec, 2, backend)
    sim.configure()
    sim.activate()
    assert sim.time.dtype == np.float64
    np.testing.assert_array_equal(sim.time, 40000.0)
    expected = 40000.0
    for _ in range(3):
        sim.step(10)
        for _ in range(10):
            expected += sim.dt
    sim.read()
    np.testing.assert_array_equal(sim.time, expected)  # one float64 addition per step, as mj_step
    sim.reset(worlds=[1])
    assert sim.time[0] == expected and sim.time[1] == 40000.0
    sim.shutdown()


def test_base_state_follows_the_free_joint_of_the_robot(backend):
    """base_state is the floating base's qpos (7) and qvel (6), refreshed by read()."""
    sim = batchsim.make("quadruped", 3, backend)
    sim.configure()
    sim.activate()
    base = sim.spec.floating_base
    assert base is not None and sim.base_state.shape == (3, 13)
    sim.step(20)
    sim.read()
    qpos, qvel = (host(sim.device_arrays()[f]).astype(np.float64) for f in ("qpos", "qvel"))
    np.testing.assert_allclose(sim.base_state[:, :7], qpos[:, base.qposadr : base.qposadr + 7], atol=1e-6)
    np.testing.assert_allclose(sim.base_state[:, 7:], qvel[:, base.dofadr : base.dofadr + 6], atol=1e-6)
    assert sim.base_state[:, 2].max() < 1.0  # it fell from its initial height
    sim.shutdown()
    assert batchsim.make("arm", 1, backend).base_state is None  # a fixed-base robot has none


def test_read_moves_each_value_once_and_actuator_states_still_read_them(backend):
    """A motor's actuator states are its joint's own state interfaces: the readings block holds
    them once (the state, the base, nothing twice; on a GPU every column comes down each
    period), and actuator_states reads them from there, as the engine has them."""
    sim = batchsim.make("humanoid", 2, backend)
    sim.configure()
    sim.activate()
    nstate = len(sim.spec.state)
    assert sim.readings.shape == (2, nstate + 13)  # 140 columns before: the actuator states again
    sim.step(5)
    sim.read()
    names = sim.export_state_interfaces()
    joints = [name for name, _, _ in sim.spec.actuator_joints]
    expected = np.concatenate(
        [sim.state[:, [names.index(f"{j}/{kind}") for j in joints]] for kind in ("position", "velocity", "effort")], axis=1
    )
    np.testing.assert_array_equal(sim.actuator_states, expected)
    qpos = host(sim.device_arrays()["qpos"]).astype(np.float64)
    adr = [q for _, q, _ in sim.spec.actuator_joints]
    np.testing.assert_allclose(sim.actuator_states[:, : len(joints)], qpos[:, adr], atol=1e-6)
    sim.shutdown()


def test_reset_returns_to_the_initial_state_not_qpos0(backend):
    """A world starts in, and resets to, spec.initial (here a ros2_control initial_value)."""
    block = """<ros2_control name="arm" type="system"><joint name="joint2">
      <command_interface name="position"/>
      <state_interface name="position"><param name="initial_value">0.5</param></state_interface>
    </joint></ros2_control>"""
    sim = batchsim.make("arm", 3, backend, ros2_control=block)
    sim.configure()
    sim.activate()
    sim.read()
    np.testing.assert_allclose(sim.state[:, 0], 0.5, atol=1e-7)
    sim.command[:, 0] = -0.5
    sim.write()
    sim.step(200)
    sim.reset(worlds=[2])
    np.testing.assert_allclose(sim.state[2, 0], 0.5, atol=1e-7)
    assert (sim.state[:2, 0] < 0.3).all()
    np.testing.assert_allclose(sim.command[2], 0.5)
    sim.shutdown()


def test_failure_lines_are_rate_limited_and_counted(monkeypatch, caplog):
    """BURST lines per WINDOW, the rest counted: at once in the same breath, or once the window
    is over when they came later; none is lost and none said twice."""
    from batchsim.parts import failures

    now = [100.0]
    monkeypatch.setattr(failures.wallclock, "monotonic", lambda: now[0])
    caplog.set_level(logging.WARNING, logger="batchsim.test")
    log = failures.FailureLog("test", 8192)

    def report(worlds: list[int], at: float) -> list[str]:
        now[0] = at
        caplog.clear()
        log.flush()
        w = np.array(worlds)
        log.report(w, ["diverged"] * len(w), ["why"] * len(w), np.full(len(w), 1.5))
        return [r.getMessage() for r in caplog.records]

    assert report([7, 9], 100.0) == [
        "batchsim: test: world 7 diverged at sim time 1.5000 s (why); frozen until reset",
        "batchsim: test: world 9 diverged at sim time 1.5000 s (why); frozen until reset",
    ]
    lines = report([1, 2, 3, 4, 5], 100.5)  # one left in the burst: it, and the count
    assert lines == [
        "batchsim: test: world 1 diverged at sim time 1.5000 s (why); frozen until reset",
        "batchsim: test: 4 more of 8192 worlds diverged in the same period (worlds 2, 3, 4, 5); frozen until reset",
    ]
    assert report([10, 11], 101.0) == []  # burst spent: held
    assert report([], 101.5) == []  # window not over
    now[0] = 102.5
    caplog.clear()
    log.flush()
    assert [r.getMessage() for r in caplog.records] == [
        "batchsim: test: 2 more of 8192 worlds diverged in the last 2 s (worlds 10, 11); frozen until reset"
    ]
    assert report([12], 102.6)[0].startswith("batchsim: test: world 12 diverged")  # a new window
