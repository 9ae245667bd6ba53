"""step()'s `meanwhile`: host work beside the device's steps, and the ROS bridge's snapshot in it.

A flat-out GPU fleet with the bridge spent the bridge's snapshot (about 0.07 ms of a 1.9 ms period
at 1024 arms) on the loop thread while the GPU sat idle: 4-6 % of its speed against the same
fleet without ROS. The snapshot now runs between the period's launch and the wait for it, and
still shows the state the period started from; a channel that reads the engine itself (tf's
body poses) is written before the launch. No ROS here: the bridge's host runs in this process
without workers, as benchmarks/bridge_period.py drives it.
"""

from __future__ import annotations

import importlib.util
import os

import numpy as np
import pytest

import batchsim
from batchsim.controllers import default_controllers, load_controllers
from batchsim.loop import Participant, SimLoop

FORCED = os.environ.get("BATCHSIM_FORCE_BACKENDS") == "1"
HAVE_WARP = importlib.util.find_spec("mujoco_warp") is not None or FORCED
NEEDS_WARP = pytest.mark.skipif(not HAVE_WARP, reason="mujoco_warp is not installed")
NEEDS_JAX = pytest.mark.skipif(importlib.util.find_spec("jax") is None and not FORCED, reason="jax is not installed")
BACKENDS = ["cpu", pytest.param("warp", marks=NEEDS_WARP)]
# and a fleet of two shards (Warp's CPU device twice, in this process): its own step()
WITH_SHARDS = [*BACKENDS, pytest.param("warp shards", marks=NEEDS_WARP)]


def active(backend: str, nworld: int = 3):
    if backend == "warp shards":
        sim = batchsim.make("arm", nworld + 1, "warp", devices=["cpu", "cpu"])
    else:
        sim = batchsim.make("arm", nworld, backend)
    sim.configure()
    sim.activate()
    return sim


@pytest.mark.parametrize("backend", [*WITH_SHARDS, pytest.param("mjx", marks=NEEDS_JAX)])
def test_meanwhile_runs_once_per_step_and_sees_the_periods_start(backend):
    sim = active(backend)
    sim.command[:] = 0.3
    sim.write()
    sim.read()
    for k in range(2):  # a fleet's first period of a length steps one shard at a time, then all at once
        start = sim.state.copy()
        seen: list = []
        sim.step(5, meanwhile=lambda seen=seen: seen.append((sim.state.copy(), sim.time.copy())))
        assert len(seen) == 1
        state, time = seen[0]
        np.testing.assert_array_equal(state, start)  # what read() filled stays until the next read()
        np.testing.assert_allclose(time, 5 * k * sim.dt)
        sim.read()
        assert not np.array_equal(sim.state, start)  # and the steps did run
    assert sim.steps_on_device == (backend != "cpu")
    sim.shutdown()


@pytest.mark.parametrize("backend", WITH_SHARDS)
def test_what_meanwhile_raises_comes_after_the_period_is_done(backend):
    """A failing hook must not leave the engine half-stepped: the steps run, the clock moves,
    then step() raises it."""
    sim = active(backend)

    def fails() -> None:
        raise RuntimeError("a hook failed")

    for k in (1, 2):  # a fleet: the first period of a length, then one all at once
        with pytest.raises(RuntimeError, match="a hook failed"):
            sim.step(5, meanwhile=fails)
        sim.read()
        np.testing.assert_allclose(sim.time, 5 * k * sim.dt)
    sim.step(5)  # and the next period runs as ever
    sim.read()
    np.testing.assert_allclose(sim.time, 15 * sim.dt)
    sim.shutdown()


def _bridge(sim):
    from ros_bridge.host import BridgeHost
    from ros_bridge.options import BridgeOptions
    from ros_bridge.plan import build_plan

    manager = load_controllers(default_controllers("arm"), sim.spec, sim.nworld)
    loop = SimLoop(sim, control_rate=100.0, rtf=0.0, participants=[manager])
    plan, fills, inputs = build_plan(sim, loop.control_rate, BridgeOptions(), manager, 1)
    host = BridgeHost(sim, loop, plan, fills, inputs, processes=False, manager=manager)  # no workers
    host.attach()
    joint_states = next(o for o in plan.outputs if o.topic == "joint_states")
    position = next(f for f in joint_states.fields if f.name == "position")
    column = {name: i for i, name in enumerate(sim.spec.state_interfaces)}
    state_columns = [column[f"{joint}/position"] for joint in joint_states.names]
    return loop, host, plan, (position, state_columns)


class _Spy:
    """A last participant: the state and body poses each period starts from."""

    def __init__(self):
        self.state, self.poses = [], []

    def update(self, sim, time, period):
        self.state.append(sim.state.copy())
        self.poses.append(sim.body_poses())


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("tf_wanted", [False, True])
def test_the_bridges_snapshot_is_written_beside_the_steps_and_shows_the_periods_start(backend, tf_wanted, monkeypatch):
    import ros_bridge.host as host_module
    from ros_bridge.protocol.snapshot import Snapshot, read_snapshot

    sim = active(backend)
    loop, host, plan, (position, state_columns) = _bridge(sim)
    if tf_wanted and plan.tf is None:
        host.close()
        sim.shutdown()
        pytest.skip("no tf in the plan: tf2_msgs is not installed")
    spy = _Spy()
    loop.participants.append(spy)
    wanted = [position.channel] + ([plan.tf.channel] if tf_wanted else [])
    host.memory["demand"][:, wanted] = 1
    stepping = {"now": False}
    engine_step = sim.engine.step

    def step(nstep, meanwhile, start):
        stepping["now"] = True
        try:
            return engine_step(nstep, meanwhile, start)
        finally:
            stepping["now"] = False

    monkeypatch.setattr(sim.engine, "step", step)
    written_while_stepping = []
    write = host_module.write_snapshot

    def spied(*args, **kwargs):
        written_while_stepping.append(stepping["now"])
        return write(*args, **kwargs)

    monkeypatch.setattr(host_module, "write_snapshot", spied)
    try:
        sim.command[:] = 0.4
        nchannel = len(plan.channels)
        for k in range(4):
            loop.run_period()
            snap = read_snapshot(host.memory, nchannel, 0, sim.nworld, Snapshot())
            assert snap is not None and snap.period == k
            published = snap.channels[position.channel][:, list(position.columns)]
            np.testing.assert_array_equal(published, spy.state[k][:, state_columns])
            if tf_wanted:
                tf = np.asarray(snap.channels[plan.tf.channel]).reshape(sim.nworld, -1, 7)
                xpos, _ = spy.poses[k]
                np.testing.assert_allclose(tf[:, :, :3], xpos[:, list(plan.tf.bodies)], atol=1e-6)
        # on a device (warp, even Warp's CPU device) the snapshot without tf runs beside the
        # steps; tf's poses are the engine's and are written before them; on cpu, before them
        expected = sim.steps_on_device and not tf_wanted
        assert written_while_stepping == [expected] * 4
    finally:
        host.close()
        sim.shutdown()


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_recording_takes_each_periods_own_snapshot(backend):
    """The recording's participant copies the newest snapshot into its ring. Taken in
    after_write, it took the one before: on a GPU the host writes this period's beside the
    steps now, after every after_write."""
    from ros_bridge.recording import Recording

    sim = active(backend)
    loop, host, plan, (position, _) = _bridge(sim)
    recording = Recording(plan, host.memory, loop)
    loop.participants.insert(loop.participants.index(host) + 1, recording)
    m = host.memory
    m["demand"][:, position.channel] = 1
    m["rec.on"][0] = 1  # as the recorder process says once it is ready
    try:
        for k in range(4):
            loop.run_period()
            slot = (int(m["rec.pos"][0]) - 1) % recording.writer.slots
            assert int(m["rec.meta"][slot][1]) == k  # (n, period, time, forced) of the snapshot taken
    finally:
        m["rec.on"][0] = 0
        host.close()
        sim.shutdown()


@pytest.mark.skipif(not HAVE_WARP, reason="mujoco_warp is not installed")
def test_warp_runs_meanwhile_before_it_waits_for_the_device(monkeypatch):
    """On a device, after the launch and before the wait (on Warp's CPU device too, whose
    graph replays at once, so the state alone cannot tell)."""
    import warp as wp

    sim = active("warp")
    sim.step(5)  # the period's graph captured
    events = []
    synchronize = wp.synchronize_device
    monkeypatch.setattr(wp, "synchronize_device", lambda *a, **k: (events.append("wait"), synchronize(*a, **k))[1])
    sim.step(5, meanwhile=lambda: events.append("meanwhile"))
    assert events[:2] == ["meanwhile", "wait"], events
    sim.shutdown()


class _Hook:
    def __init__(self, fails: bool):
        self.fails, self.ran = fails, 0

    def update(self, sim, time, period):
        pass

    def while_stepping(self, sim, time, period):
        self.ran += 1
        if self.fails:
            raise RuntimeError("a hook failed")


def test_a_failing_while_stepping_hook_leaves_the_loops_clock_with_the_engine():
    """The period ran, so the loop counts it; every other hook ran too; then the error."""
    sim = active("cpu")
    failing, other = _Hook(True), _Hook(False)
    loop = SimLoop(sim, control_rate=100.0, rtf=0.0, participants=[failing, other])
    with pytest.raises(RuntimeError, match="a hook failed"):
        loop.run_period()
    assert other.ran == 1 and loop.stats.periods == 1
    sim.read()
    np.testing.assert_allclose(sim.time, loop.sim_time)
    sim.shutdown()


def test_participants_subclass_participant_or_are_duck_typed_and_the_list_may_change(monkeypatch):
    """Participant's hooks are no-ops the loop skips (no while_stepping: the system gets no
    `meanwhile`); a duck-typed object's hooks run as a subclass's; a participant appended or
    replaced in the plain list runs from the next period."""
    sim = active("cpu")
    calls: list[str] = []
    meanwhile: list[bool] = []
    step = sim.step
    monkeypatch.setattr(sim, "step", lambda nstep, meanwhile=None, step=step, seen=meanwhile: (seen.append(meanwhile is not None), step(nstep, meanwhile))[1])

    class Sub(Participant):
        def update(self, sim, time, period):
            calls.append("sub.update")

    class Duck:
        def update(self, sim, time, period):
            calls.append("duck.update")

        def after_write(self, sim, time, period):
            calls.append("duck.after_write")

        def while_stepping(self, sim, time, period):
            calls.append("duck.while_stepping")

    loop = SimLoop(sim, control_rate=100.0, rtf=0.0, participants=[Sub()])
    loop.run_period()
    assert calls == ["sub.update"] and meanwhile == [False]
    loop.participants.append(Duck())
    calls.clear()
    loop.run_period()
    assert calls == ["sub.update", "duck.update", "duck.after_write", "duck.while_stepping"] and meanwhile[-1]
    loop.participants[1] = Sub()
    calls.clear()
    loop.run_period()
    assert calls == ["sub.update", "sub.update"] and not meanwhile[-1]
    sim.shutdown()


class _LateDemand:
    """After the bridge's after_write: a subscriber to tf arrives, and a shard writes a
    world's status, both before the bridge's snapshot beside the steps."""

    def __init__(self, memory, channel, at):
        self.memory, self.channel, self.at, self.period = memory, channel, at, 0

    def update(self, sim, time, period):
        pass

    def after_write(self, sim, time, period):
        if self.period == self.at:
            self.memory["demand"][:, self.channel] = 1
            sim.status[0] |= np.uint8(batchsim.Status.BAD_COMMAND)  # as a shard's step would write it
        self.period += 1


@pytest.mark.parametrize("backend", BACKENDS)
def test_what_arrives_after_after_write_waits_for_the_next_snapshot(backend):
    """The snapshot written beside the steps is the one after_write decided on, with the status
    of that moment: a tf subscriber arriving in between gets tf from the next period on,
    written before the steps (a fill that reads the engine beside them read post-step poses on
    a GPU, and on a fleet of shard processes stopped the loop)."""
    from ros_bridge.protocol.snapshot import Snapshot, read_snapshot

    sim = active(backend)
    loop, host, plan, (position, state_columns) = _bridge(sim)
    if plan.tf is None:
        host.close()
        sim.shutdown()
        pytest.skip("no tf in the plan: tf2_msgs is not installed")
    spy = _Spy()
    loop.participants += [_LateDemand(host.memory, plan.tf.channel, at=1), spy]
    host.memory["demand"][:, position.channel] = 1
    nchannel = len(plan.channels)
    try:
        sim.command[:] = 0.4
        for k in range(3):
            loop.run_period()
            snap = read_snapshot(host.memory, nchannel, 0, sim.nworld, Snapshot())
            assert snap.period == k
            np.testing.assert_array_equal(snap.channels[position.channel][:, list(position.columns)], spy.state[k][:, state_columns])
            if k == 1:  # decided without tf: none now, and the status of after_write's moment
                assert plan.tf.channel not in snap.channels
                assert not snap.status[0] & np.uint8(batchsim.Status.BAD_COMMAND)
            if k == 2:
                tf = np.asarray(snap.channels[plan.tf.channel]).reshape(sim.nworld, -1, 7)
                np.testing.assert_allclose(tf[:, :, :3], spy.poses[k][0][:, list(plan.tf.bodies)], atol=1e-6)
    finally:
        host.close()
        sim.shutdown()


def _trajectory_batch(worlds, njoint, position):
    """One 2-point trajectory per world, to `position` (a NaN is refused by the controller)."""
    from batchsim.controllers import TrajectoryBatch

    n = len(worlds)
    positions = np.full((2 * n, njoint), position)
    return TrajectoryBatch(
        worlds=np.asarray(worlds, np.int64),
        start_time=np.zeros(n),
        joint_mask=np.ones((n, njoint), bool),
        offsets=np.arange(n + 1, dtype=np.int64) * 2,
        times=np.tile([0.05, 0.1], n),
        positions=positions,
    )


class _Pending:
    """A participant between the bridge and the controllers: whether each period's update
    finds world 0's trajectory queued (handed over) before the controllers run."""

    def __init__(self, jtc):
        self.jtc, self.seen = jtc, []

    def update(self, sim, time, period):
        self.seen.append((bool(self.jtc.pending[0]), bool(self.jtc.executing[0])))


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_bridge_hands_trajectories_over_beside_the_steps_and_they_start_at_the_next_update(backend):
    """A burst of 4096 trajectories cost its period ~2.2 ms of validation and queueing on the loop's
    thread (5 ms on the GPU hosts), on top of the controllers' update and the physics: over the 10 ms
    period. The bridge now hands a period's trajectories to their controllers while the device
    steps, and they start at the next update, as upstream's subscriber callback hands a message to
    the controller's next update. A refused one sets BAD_COMMAND from the next period on."""
    from batchsim.memory import Ring
    from ros_bridge.protocol.requests import Kind, encode_trajectories

    sim = active(backend)
    loop, host, plan, _ = _bridge(sim)
    jtc = loop.participants[1]["joint_trajectory_controller"]
    spy = _Pending(jtc)
    loop.participants.insert(1, spy)  # after the bridge's update, before the controllers'
    (index, spec), = [(i, s) for i, s in enumerate(plan.inputs) if s.topic.endswith("joint_trajectory")]
    try:
        loop.run_period()  # the controllers hold where the arms are
        batch = _trajectory_batch([0, 2], len(jtc.joints), 0.2)
        batch.positions[2:] = np.nan  # world 2's is refused
        assert Ring(host.memory, "ring0").put(Kind.TRAJECTORY, encode_trajectories(index, batch))
        np.add.at(host.memory[f"{spec.slots}.seq"], batch.worlds, 1)
        loop.run_period()  # taken from the ring, queued beside the steps
        assert spy.seen[1] == (False, False) and jtc.pending[0] and not jtc.executing[0]
        bad = np.uint8(batchsim.Status.BAD_COMMAND)
        assert not (sim.status & bad).any()
        loop.run_period()  # started by this period's update
        assert spy.seen[2] == (True, False) and jtc.executing[0] and not jtc.pending[0]
        assert sim.status[2] & bad and not sim.status[0] & bad and not jtc.pending[2]
    finally:
        host.close()
        sim.shutdown()


def test_a_reset_before_the_hand_over_drops_the_reset_worlds_waiting_trajectories():
    """Taken in update(), handed over beside the steps: a reset in between (a reset_world request
    served after the ring was read) drops its worlds' trajectories, as it drops a queued one."""
    from batchsim.controllers.topics import Input, MessageKind
    from batchsim.memory import Layout, Memory
    from ros_bridge.protocol.goals import refusal_arrays
    from ros_bridge.trajectory_inputs import TrajectoryInputs

    memory = Memory.create(Layout([("traj.seq", (4,), "int64"), *refusal_arrays(4)]), shared=False)
    got = []

    def apply(batch):
        got.append(batch.worlds.tolist())
        return [(k, "bad") for k in range(len(batch)) if batch.worlds[k] == 3]

    def refused(index, worlds, rejections, good, rejected):  # as the bridge's bookkeeping
        for k, _ in rejections:
            good[worlds[k]], rejected[worlds[k]] = False, True

    inputs = [Input("t", MessageKind.JOINT_TRAJECTORY, apply)]
    trajectories = TrajectoryInputs(memory, [MessageKind.JOINT_TRAJECTORY], ["traj"], inputs, refused, 4)
    try:
        trajectories.take({0: [_trajectory_batch([0, 1, 3], 2, 0.1)]}, None, False, None, None, later=True)
        assert trajectories.waiting == 1 and not got
        trajectories.forget(np.array([1]))
        trajectories.hand_over(beside_steps=True)
        assert got == [[0, 3]] and trajectories.waiting == 0
        good, rejected = np.zeros(4, bool), np.zeros(4, bool)
        trajectories.verdicts(good, rejected)  # the next update's: world 0 accepted, world 3 refused
        assert good.tolist() == [True, False, False, False] and rejected.tolist() == [False, False, False, True]
        good, rejected = np.zeros(4, bool), np.zeros(4, bool)
        trajectories.verdicts(good, rejected)  # taken once
        assert not good.any() and not rejected.any()
        trajectories.take({0: [_trajectory_batch([2], 2, 0.1)]}, None, False, None, None, later=True)
        trajectories.forget(slice(None))  # every world reset
        trajectories.hand_over(beside_steps=True)
        assert got == [[0, 3]]
    finally:
        memory.close()


def test_a_goal_the_loop_does_not_take_is_refused_with_its_reason_or_the_reset():
    """A FollowJointTrajectory goal its controller refuses reaches its worker as Refusal.INVALID
    with the controller's reason; one a reset drops before the hand-over as Refusal.RESET, where
    its worker used to wait UNSEEN_TIMEOUT (5 s) and abort it as 'not taken'. A refused topic
    trajectory (tag 0) marks nothing."""
    from batchsim.controllers.topics import Input, MessageKind
    from batchsim.memory import Layout, Memory
    from ros_bridge.protocol.goals import Refusal, RefusalReader, refusal_arrays
    from ros_bridge.trajectory_inputs import TrajectoryInputs

    memory = Memory.create(Layout([("traj.seq", (4,), "int64"), *refusal_arrays(4)]), shared=False)

    def apply(batch):
        return [(k, "jtc: the trajectory lacks joint 'j1': it is: not partial") for k in range(len(batch)) if batch.worlds[k] in (1, 2)]

    def goals(worlds, tags):
        batch = _trajectory_batch(worlds, 2, 0.1)
        batch.goals = np.asarray(tags, np.int64)
        return batch

    inputs = [Input("t", MessageKind.JOINT_TRAJECTORY, apply)]
    trajectories = TrajectoryInputs(memory, [MessageKind.JOINT_TRAJECTORY], ["traj"], inputs, lambda *a: None, 4)
    reader = RefusalReader(memory)
    try:
        trajectories.take({0: [goals([0, 1, 2], [11, 12, 0])]}, None, False, None, None, later=False)
        assert reader.refused(0, 11) is None  # taken
        assert reader.refused(1, 12) == (Refusal.INVALID, "jtc: the trajectory lacks joint 'j1': it is: not partial")
        assert memory["goal.refused"][2] == 0  # a topic trajectory's refusal is the bridge's rejection alone
        trajectories.take({0: [goals([0, 3], [13, 14])]}, None, False, None, None, later=True)
        trajectories.forget(np.array([3]))  # world 3 reset before the hand-over
        assert reader.refused(3, 14) == (Refusal.RESET, "the world was reset")
        trajectories.take({0: [goals([1], [15])]}, np.array([1]), True, None, None, later=False)  # with its reset
        assert reader.refused(1, 15) == (Refusal.RESET, "the world was reset") and reader.refused(0, 13) is None
    finally:
        memory.close()


def _ring_trajectory(host, plan, batch):
    """Put a trajectory batch in worker 0's ring, as a worker does (ros_bridge/worker/trajectories.py)."""
    from batchsim.memory import Ring
    from ros_bridge.protocol.requests import Kind, encode_trajectories

    (index, spec), = [(i, s) for i, s in enumerate(plan.inputs) if s.topic.endswith("joint_trajectory")]
    assert Ring(host.memory, "ring0").put(Kind.TRAJECTORY, encode_trajectories(index, batch))
    np.add.at(host.memory[f"{spec.slots}.seq"], batch.worlds, 1)


def test_a_goal_that_comes_with_a_switch_that_deactivates_its_controller_is_aborted_as_before():
    """A review found: handed over beside the steps, a FollowJointTrajectory goal read from the ring
    together with a switch_controller deactivating its controller reached the controller after the
    switch had reset it, and stayed ACTIVE on an inactive controller. A read holding a switch now
    hands its trajectories over at once, before the switch takes effect, as before."""
    from batchsim.controllers.topics import GoalOutcome
    from batchsim.memory import Ring
    from ros_bridge.protocol.requests import Kind, encode_switch

    sim = active("cpu")
    loop, host, plan, _ = _bridge(sim)
    manager = loop.participants[1]
    jtc = manager["joint_trajectory_controller"]
    try:
        loop.run_period()
        ring = Ring(host.memory, "ring0")
        assert ring.put(Kind.SWITCH, encode_switch(1, 0, [], ["joint_trajectory_controller"], 1, False))
        batch = _trajectory_batch([0], len(jtc.joints), 0.2)
        batch.goals = np.array([7])
        _ring_trajectory(host, plan, batch)
        for _ in range(3):
            loop.run_period()
        assert not manager.active("joint_trajectory_controller")[0]
        # ended by the deactivation (the bridge words it as upstream: aborted, "Current goal
        # cancelled during deactivate transition.")
        assert jtc.outcome[0] == GoalOutcome.DEACTIVATED and not jtc.pending[0] and not jtc.executing[0]
    finally:
        host.close()
        sim.shutdown()


def test_a_trajectory_refused_beside_the_last_steps_shows_bad_command_while_paused():
    """A step run while paused hands its trajectories over beside its steps; one refused there
    shows BAD_COMMAND in what is published at once while paused, not only after the next period."""
    from ros_bridge.protocol.snapshot import Snapshot, read_snapshot

    sim = active("cpu")
    loop, host, plan, _ = _bridge(sim)
    jtc = loop.participants[1]["joint_trajectory_controller"]
    try:
        loop.run_period()
        batch = _trajectory_batch([1], len(jtc.joints), np.nan)  # refused
        _ring_trajectory(host, plan, batch)
        loop.run_period()  # the one step_simulation runs while paused
        host.idle(sim, loop.sim_time)
        snap = read_snapshot(host.memory, len(plan.channels), 0, sim.nworld, Snapshot())
        bad = np.uint8(batchsim.Status.BAD_COMMAND)
        assert snap.status[1] & bad and not snap.status[0] & bad
    finally:
        host.close()
        sim.shutdown()


def test_a_goal_canceled_in_the_ring_read_that_brought_it_is_canceled():
    """A review found that a FollowJointTrajectory goal and its cancel in one ring read (a client
    that cancels within a period) had the cancel served first, when the goal was not there yet, so
    the goal ran. Cancels are now served after the read's trajectories."""
    from batchsim.controllers.topics import GoalOutcome
    from batchsim.memory import Ring
    from ros_bridge.action_plan import encode_cancel
    from ros_bridge.protocol.requests import Kind

    sim = active("cpu")
    loop, host, plan, _ = _bridge(sim)
    jtc = loop.participants[1]["joint_trajectory_controller"]
    (action,) = [a for a, spec in enumerate(plan.actions) if spec.controller == "joint_trajectory_controller"]
    try:
        loop.run_period()
        batch = _trajectory_batch([0, 1], len(jtc.joints), 0.2)
        batch.goals = np.array([7, 8])
        _ring_trajectory(host, plan, batch)
        assert Ring(host.memory, "ring0").put(Kind.CANCEL, encode_cancel(action, 0, 7))
        for _ in range(2):
            loop.run_period()
        assert jtc.outcome[0] == GoalOutcome.CANCELED and not jtc.executing[0]
        assert jtc.outcome[1] == GoalOutcome.ACTIVE and jtc.executing[1]  # the other world's goal runs
    finally:
        host.close()
        sim.shutdown()


def test_a_recording_stopped_before_its_recorder_is_up_holds_the_periods_between(tmp_path):
    """`/batchsim/record` answers at once and the recorder process takes a second or more to
    come up. The ring took periods only once it said ready, so start, 1.5 s, stop on a loaded
    machine gave a file of no messages (and a late `ready` turned writing on after the stop)."""
    from mcap.reader import make_reader

    from ros_bridge.recording import Recording

    sim = active("cpu")
    loop, host, plan, _ = _bridge(sim)
    recording = Recording(plan, host.memory, loop)
    loop.participants.insert(loop.participants.index(host) + 1, recording)
    path = tmp_path / "early.mcap"
    try:
        assert recording.start(str(path))[0]
        for _ in range(5):  # in a few ms: the recorder is still importing
            loop.run_period()
        recording.stop(timeout=60)
        assert not host.memory["rec.on"][0]
        loop.run_period()  # after the stop: not in the file
    finally:
        recording.close()
        host.close()
        sim.shutdown()
    with open(path, "rb") as f:
        topics = [channel.topic for _, channel, _ in make_reader(f).iter_messages()]
    assert topics.count("/world_0/joint_states") == 5, sorted(set(topics))


def test_a_record_request_older_than_its_services_wait_is_dropped_not_carried_out_late(tmp_path, monkeypatch):
    """Asked during start-up (the first period may compile for a minute), `/batchsim/record`
    answered "did not answer in time" and the loop started the recording later anyway."""
    from ros_bridge.protocol.recording import answer, put_request
    from ros_bridge.recording import Recording

    monkeypatch.chdir(tmp_path)  # where a dated recording would go
    sim = active("cpu")
    loop, host, plan, _ = _bridge(sim)
    recording = Recording(plan, host.memory, loop)
    loop.participants.insert(loop.participants.index(host) + 1, recording)
    m = host.memory
    try:
        put_request(m, 1, True)
        m["rec.req"][2] -= 5_000_000_000  # asked 5 s ago: its service gave up after 2
        loop.run_period()
        ok, message = answer(m, 1)
        assert not ok and "dropped" in message and not m["rec.on"][0]
        put_request(m, 2, True)  # a fresh one starts
        loop.run_period()
        assert answer(m, 2)[0] and m["rec.on"][0]
    finally:
        recording.close()
        host.close()
        sim.shutdown()
    assert len(list(tmp_path.glob("*.mcap"))) == 1
