"""The bridge's parts without a ROS graph: names, command rules and slots, the log throttle,
shared memory and its rings, request records, options and the plan."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

import batchsim
from batchsim.controllers import default_controllers, load_controllers
from batchsim.controllers.topics import TrajectoryBatch
from batchsim.loop import OptionError, RateError, SimLoop, whole_ratio
from batchsim.memory import Layout, Memory, Ring, ring_arrays
from batchsim.types import split_worlds
from ros_bridge.naming import NamingError, ros_name, ros_names, world_namespaces
from ros_bridge.options import BridgeOptions, default_workers
from ros_bridge.plan import build_plan
from ros_bridge.protocol.commands import (
    Problem,
    RejectionWriter,
    SlotReader,
    SlotWriter,
    check_single,
    check_vector,
    rejection_arrays,
    slot_arrays,
)
from ros_bridge.protocol.requests import (
    Kind,
    concatenate,
    decode_reset,
    decode_trajectories,
    encode_reset,
    encode_trajectories,
)
from ros_bridge.protocol.snapshot import (
    BACKLOG,
    HEADERS,
    SLOTS,
    Snapshot,
    read_snapshot,
    reset_snapshots,
    snapshot_arrays,
    write_snapshot,
)
from ros_bridge.throttle import LogThrottle
from ros_bridge.worker.graph_scan import SLICE, GraphScan

IFACES = [f"joint{i}/position" for i in range(1, 4)]


# --- naming ---
def test_ros_names_are_tokens_and_distinct():
    assert ros_name("wrist.force") == "wrist_force"
    assert ros_name("3d cam") == "_3d_cam"
    assert ros_names(["a.b", "a-b", "a_b"]) == ["a_b", "a_b_2", "a_b_3"]


def test_world_namespaces_with_offset_and_the_plugin_namespace():
    assert world_namespaces(3) == ["world_0", "world_1", "world_2"]
    assert world_namespaces(2, "robot_{i}/", offset=4096) == ["robot_4096", "robot_4097"]
    assert world_namespaces(1, plugin_namespace="car/") == ["car"]
    assert world_namespaces(1, plugin_namespace="car/", offset=3) == ["world_3"]  # a fleet's member, not the plugin's


@pytest.mark.parametrize(
    "nworld, template, message",
    [
        (2, "robot", "namespace 'robot' has no {i}: 2 worlds need distinct namespaces"),
        (2, "r_{i}_{j}", "namespace 'r_{i}_{j}': only {i} may be substituted"),
        (2, "{i}", "namespace '{i}' gives '0', which is not a valid ROS namespace"),
    ],
)
def test_bad_namespace_templates_name_the_option_not_a_flag(nworld, template, message):
    with pytest.raises(NamingError) as e:
        world_namespaces(nworld, template)
    assert str(e.value).startswith(message)
    assert e.value.option == "namespace" and "--" not in str(e.value)
    assert e.value.named("--namespace").startswith("--" + message)


# --- commands ---
def test_check_vector_names_the_problem():
    owners = [""] * 3
    assert check_vector(np.array([0.1, 0.2, 0.3]), IFACES, owners) is None
    assert check_vector(np.array([0.1, 0.2]), IFACES, owners)[0] is Problem.LENGTH
    problem, text = check_vector(np.array([0.1, math.nan, 0.3]), IFACES, owners)
    assert problem is Problem.NOT_FINITE and "joint2/position" in text
    problem, text = check_vector(np.array([0.1, 0.2, -2e10]), IFACES, owners)
    assert problem is Problem.RANGE and "joint3/position" in text
    problem, text = check_vector(np.array([0.1, 0.2, 0.3]), IFACES, ["", "jtc", ""])
    assert problem is Problem.CLAIMED and "'jtc'" in text


def test_check_single_names_the_problem():
    owners = ["", "jtc", ""]
    assert check_single(0.5, 0, IFACES, owners) is None
    assert check_single(math.inf, 0, IFACES, owners)[0] is Problem.NOT_FINITE
    assert check_single(1e11, 2, IFACES, owners)[0] is Problem.RANGE
    assert check_single(0.5, 1, IFACES, owners) == (Problem.CLAIMED, "joint2/position is claimed by controller 'jtc'")


def test_slots_deliver_each_command_once_and_a_new_writer_replays_nothing():
    layout = Layout(slot_arrays("cmd", 4, 3, per_column=True))
    memory = Memory.create(layout, shared=False)
    writer, reader = SlotWriter(memory, "cmd"), SlotReader(memory, "cmd")
    writer.put_row(2, np.array([1.0, 2.0, 3.0]))
    writer.put(3, 1, -0.5)
    assert reader.fresh()[2].all() and reader.fresh()[3, 1]
    new, values = reader.take()
    assert new.sum() == 4 and new[2].all() and new[3, 1]
    np.testing.assert_array_equal(values[2], [1, 2, 3])
    assert not reader.take()[0].any()  # taken once
    # a restarted worker writes through the same counters: only its own commands are new
    again = SlotWriter(memory, "cmd")
    again.put(0, 0, 9.0)
    new, _ = reader.take()
    assert new.sum() == 1 and new[0, 0]
    # what arrived for reset worlds is dropped
    again.put_row(1, np.zeros(3))
    reader.drop(np.array([1]))
    assert not reader.take()[0].any()


def test_rejections_keep_a_count_and_the_last_reason_per_world():
    memory = Memory.create(Layout(rejection_arrays("rej", 2)), shared=False)
    rejections = RejectionWriter(memory, "rej")
    rejections.put(1, 7, "/world_1/commands", "2 values, expected 6")
    rejections.put(1, 9, "/world_1/commands", "value nan is not finite: a: b")
    assert int(rejections.count[1]) == 2 and int(rejections.period[1]) == 9
    assert rejections.reason(1) == "/world_1/commands: value nan is not finite: a: b"
    assert rejections.topic(1) == "/world_1/commands"
    assert rejections.reason(0) == "" and int(rejections.count[0]) == 0
    rejections.put(0, 1, "/world_0/commands", "x" * 1000, count=3)  # clipped, never spilling into the next world's field
    assert len(rejections.reason(0)) == 239 and rejections.reason(1).startswith("/world_1")
    assert rejections.topic(0) == "/world_0/commands" and int(rejections.count[0]) == 3


# --- the log throttle ---
def test_throttle_keys_on_topic_and_reason_and_reports_what_it_held_back():
    now = [0.0]
    lines: list[str] = []
    throttle = LogThrottle(lines.append, interval=2.0, clock=lambda: now[0])
    topic = "/world_1/commands"
    assert throttle.warn((topic, Problem.NOT_FINITE), "nan")
    assert throttle.warn((topic, Problem.NOT_FINITE.value + "x"), "inf")  # another reason: its own line
    assert throttle.warn((topic, Problem.LENGTH), "length")
    for _ in range(3):
        now[0] += 0.1
        assert not throttle.warn((topic, Problem.NOT_FINITE), "nan again")
    assert lines == ["nan", "inf", "length"]
    now[0] = 1.9
    throttle.flush()
    assert len(lines) == 3  # the window is still open
    now[0] = 2.05
    throttle.flush()
    assert lines[3] == "nan again (3 lines like it held back in 2 s)"
    throttle.flush()
    assert len(lines) == 4  # reported once; the quiet windows closed silently
    assert throttle.warn((topic, Problem.NOT_FINITE), "nan after the window")


# --- shared memory and rings ---
def test_shared_memory_is_seen_by_an_attached_view_and_unlinked_by_its_creator():
    layout = Layout([("a", (4, 3), "f8"), ("b", (5,), "u1")])
    created = Memory.create(layout)
    attached = Memory.attach(layout, created.name)
    created["a"][2] = [1.0, 2.0, 3.0]
    attached["b"][4] = 7
    np.testing.assert_array_equal(attached["a"][2], [1, 2, 3])
    assert created["b"][4] == 7
    assert created.name.startswith("batchsim_")
    attached.close()
    created.close()
    with pytest.raises(FileNotFoundError):
        Memory.attach(layout, created.name)


def test_a_segment_that_does_not_fit_in_dev_shm_is_refused_with_one_line(monkeypatch):
    """Before this, a fleet whose segment outgrew /dev/shm died of SIGBUS (exit 135, no line)."""
    from conftest import fake_shm_free

    from batchsim.memory import SharedMemoryFull

    fake_shm_free(monkeypatch, 1 << 20)
    with pytest.raises(SharedMemoryFull) as e:
        Memory.create(Layout([("big", (2 << 20,), "u1")]))
    assert str(e.value).startswith("shared memory: this fleet needs 2 MiB in /dev/shm and 1 MiB are free (of 64)")
    Memory.create(Layout([("small", (1000,), "u1")])).close()  # what fits is made


def test_a_late_worker_reads_every_snapshot_it_missed_in_order():
    """joint_states at 25 Hz in a 100 Hz loop are in one snapshot of four: a worker woken after
    the next snapshot was written read only the newest and lost them (4096 arms on a GPU host:
    0.90-0.946 of the joint_states published, the workers stalling in graph scans); then one
    late by more than one such period still skipped those a later snapshot also held (0.970)."""
    assert 2 + SLOTS <= BACKLOG  # the first late read below is a backlog it walks one by one
    nworld = 3
    m = Memory.create(Layout([*snapshot_arrays(nworld, [2, 1]), ("demand", (1, 2), "u1")]), shared=False)
    m["demand"][:] = 1
    reset_snapshots(m)
    zeros = np.zeros(nworld, np.uint8)

    def write(n: int, *due: bool) -> None:
        fills = [lambda out, n=n: out.fill(float(n)), lambda out, n=n: out.fill(-float(n))]
        write_snapshot(m, n, n, 0.01 * n, False, zeros, zeros, fills, list(due))

    seen = Snapshot()
    write(0, True, True)
    assert read_snapshot(m, 2, 0, nworld, seen, catch_up=True).n == 0
    write(1, False, True)
    write(2, True, True)  # channel 0 due, then SLOTS + 1 snapshots without it
    last = 3 + SLOTS
    for n in range(3, last + 1):
        write(n, False, True)
    got = []
    while (snap := read_snapshot(m, 2, 1, 3, seen, catch_up=True)) is not None:
        got.append((snap.n, sorted(snap.channels)))
    # channel 0 only in 2; channel 1 in every snapshot, its rows in 1..3 overwritten since
    assert got == [(1, []), (2, [0]), (3, [])] + [(n, [1]) for n in range(4, last + 1)], got
    # without catch_up (the view), the newest only
    k = last + 1
    write(k, True, False)
    write(k + 1, False, True)
    assert read_snapshot(m, 2, 0, nworld, Snapshot()).n == k + 1
    fresh = read_snapshot(m, 2, 0, nworld, seen, catch_up=True)
    assert fresh.n == k and fresh.channels[0].tolist() == [[float(k)] * 2] * 3
    # HEADERS - 1 periods late, far more than BACKLOG snapshots behind: k+2's header is gone; it
    # skips to the oldest holding a channel no later one holds, k+4 (channel 0's newest)
    late = Snapshot()
    late.n = k + 1
    write(k + 2, True, False)
    write(k + 3, True, False)
    write(k + 4, True, False)
    for n in range(k + 5, k + 5 + HEADERS - 3):
        write(n, False, True)
    snap = read_snapshot(m, 2, 0, nworld, late, catch_up=True)
    assert snap.n == k + 4 and snap.channels[0].tolist() == [[float(k + 4)] * 2] * 3
    m.close()


def test_a_worker_a_fifth_of_a_second_late_still_publishes_every_25_hz_channel():
    """A 512-world worker is now and then late by more than 0.1 s (publishing its worlds,
    their /diagnostics): at 16 headers and 3 slots per channel, 4096 arms at 25 Hz published
    0.970 of their joint_states on an H100 host. 0.2 s late, every write is still there."""
    nworld = 2
    m = Memory.create(Layout([*snapshot_arrays(nworld, [1]), ("demand", (1, 1), "u1")]), shared=False)
    m["demand"][:] = 1
    reset_snapshots(m)
    zeros = np.zeros(nworld, np.uint8)
    for n in range(21):  # 0.2 s of a 100 Hz loop, the channel due every fourth period
        write_snapshot(m, n, n, 0.01 * n, False, zeros, zeros, [lambda out, n=n: out.fill(float(n))], [n % 4 == 0])
    seen, got = Snapshot(), []
    while (snap := read_snapshot(m, 1, 0, nworld, seen, catch_up=True)) is not None:
        if 0 in snap.channels:
            got.append(float(snap.channels[0][0, 0]))
    assert got == [0.0, 4.0, 8.0, 12.0, 16.0, 20.0]
    m.close()


def test_an_output_counts_the_periods_it_was_due_in_and_missed():
    """What a worker could not publish (its snapshots overwritten before it read them) is
    counted per topic and world, so that a benchmark can tell a worker's loss from the
    DDS's: 4096 arms on a GPU host published 0.97 of their joint_states, the rest untraced."""
    from ros_bridge.worker.snapshot import Output

    sim = batchsim.make("arm", 4, "cpu")
    sim.configure()
    plan, _fills, _inputs = build_plan(sim, 100.0, BridgeOptions(publish_rate=25), None, 1)
    spec = next(o for o in plan.outputs if o.topic == "joint_states")
    assert spec.every == 4
    out = Output(spec, plan.namespaces)

    def snap(period: int, forced: bool = False) -> Snapshot:
        s = Snapshot()
        s.period, s.forced = period, forced
        return s

    out.rows = [0, 1]
    assert [out.missed(snap(p)) for p in (0, 4, 8)] == [0, 0, 0]
    assert out.missed(snap(20)) == 2  # 12 and 16 gone
    assert out.missed(snap(21, forced=True)) == 0 and out.missed(snap(24)) == 0
    out.rows = []
    out.rows = [3]  # published again after a pause with nobody listening: nothing missed
    assert out.missed(snap(60)) == 0 and out.missed(snap(68)) == 1


def test_the_graph_scan_looks_at_a_slice_of_the_names_a_tick_and_passes_every_interval():
    """One pass over a 4096-world graph (~8,000 topics, ~6 us a name) in one tick stalled a
    worker ~60 ms: now at most SLICE names a tick."""

    class Node:
        lists = 0

        def get_topic_names_and_types(self):
            Node.lists += 1
            return [(f"/world_{i}/joint_states", ["sensor_msgs/msg/JointState"]) for i in range(2 * SLICE + 5)]

    seen: list[list[str]] = []
    passes: list[int] = []
    scan = GraphScan(Node(), lambda name: seen[-1].append(name), lambda topics: passes.append(len(topics)), every=1.0)
    for now in (0.0, 0.01, 0.02, 0.03):
        seen.append([])
        scan.step(now)
    assert [len(s) for s in seen] == [SLICE, SLICE, 5, 0] and passes == [2 * SLICE + 5]
    assert len({n for s in seen for n in s}) == 2 * SLICE + 5 and Node.lists == 1
    seen.append([])
    scan.step(1.01)  # a second after the pass ended
    assert passes == [2 * SLICE + 5] and seen[-1] == []
    scan.step(1.03)
    assert Node.lists == 2 and len(seen[-1]) == SLICE


def test_the_graph_scan_of_a_small_graph_passes_every_few_tenths_and_a_slow_one_at_most_a_second():
    """A small fleet's on-request topic (a camera's image_raw) was created up to a second after a
    subscriber appeared (issue 47: the first frame): the wait follows what a pass takes."""
    from ros_bridge.worker.graph_scan import GRAPH_SCAN, MIN_SCAN

    class Node:
        lists = 0

        def get_topic_names_and_types(self):
            Node.lists += 1
            return [("/world_0/joint_states", ["sensor_msgs/msg/JointState"])]

    slow = {"on": False}

    def on_topic(name):
        if slow["on"]:
            time.sleep(0.05)  # a pass of 50 ms: 2.5 s at 2 % of the worker, held to GRAPH_SCAN

    scan = GraphScan(Node(), on_topic, lambda topics: None)
    scan.step(0.0)
    scan.step(MIN_SCAN - 0.01)
    assert Node.lists == 1
    scan.step(MIN_SCAN + 0.01)
    assert Node.lists == 2
    slow["on"] = True
    scan.step(1.0)  # the pass that ends at 1.0 took 50 ms
    slow["on"] = False
    scan.step(1.0 + GRAPH_SCAN - 0.01)
    assert Node.lists == 3
    scan.step(1.0 + GRAPH_SCAN + 0.01)
    assert Node.lists == 4


def test_ring_wraps_refuses_when_full_and_continues_across_writers():
    layout = Layout(ring_arrays("r", 256))
    memory = Memory.create(layout, shared=False)
    producer, consumer = Ring(memory, "r"), Ring(memory, "r")
    got = []
    for k in range(40):  # many times around the ring
        assert producer.put(1, np.full(5 + k % 7, k, np.uint8))
        if k % 3 == 2:
            got += [(kind, int(p[0])) for kind, p in consumer.take()]
    got += [(kind, int(p[0])) for kind, p in consumer.take()]
    assert got == [(1, k) for k in range(40)]
    while producer.put(2, b"12345678"):
        pass
    assert not producer.put(2, b"x")  # full: refused, nothing written
    assert len(list(consumer.take())) > 0 and producer.put(2, b"x")
    assert not producer.put(1, bytes(200))  # more than half the ring: never fits
    assert [p[:1].tobytes() for _, p in Ring(memory, "r").take()] == [b"x"]


def test_a_text_record_reads_back_whole_where_an_older_record_lay():
    """The soak's fleet died after 27 minutes, twice (issue 47's 30-minute soak): a switch_controller
    request landed where an older, longer record had been, its padding to 8 bytes still held that
    record's bytes, and decode_switch's JSON read them as "Extra data" in the loop thread."""
    from ros_bridge.protocol.requests import decode_document, decode_switch, encode_document, encode_switch

    layout = Layout(ring_arrays("r", 256))
    memory = Memory.create(layout, shared=False)
    producer, consumer = Ring(memory, "r"), Ring(memory, "r")
    for _ in range(8):  # around the ring with records of non-zero bytes, to every offset
        for size in range(1, 30, 3):
            assert producer.put(1, bytes([0xAB]) * size)
            list(consumer.take())
    for n in range(40):  # every length of text record, so every length of padding
        name = "c" * n
        assert producer.put(5, encode_switch(n, 2, [name], [], 1, False))
        assert producer.put(9, encode_document(n, 3, {"controller": name}))
        records = list(consumer.take())
        assert decode_switch(records[0][1])[2] == [name]
        assert decode_document(records[1][1])[2] == {"controller": name}


def test_trajectory_batches_survive_the_ring_and_concatenate():
    nj = 3
    batch = TrajectoryBatch(
        worlds=np.array([4, 1]),
        start_time=np.array([0.0, 2.5]),
        joint_mask=np.array([[True, True, False], [True, True, True]]),
        offsets=np.array([0, 2, 3]),
        times=np.array([0.5, 1.0, 0.25]),
        positions=np.arange(9.0).reshape(3, nj),
        velocities=np.ones((3, nj)),
        has_velocities=np.array([False, True]),
    )
    index, back = decode_trajectories(np.frombuffer(encode_trajectories(2, batch), np.uint8))
    assert index == 2
    for field in ("worlds", "start_time", "joint_mask", "offsets", "times", "positions", "velocities", "has_velocities"):
        np.testing.assert_array_equal(getattr(back, field), getattr(batch, field), err_msg=field)
    assert back.accelerations is None and not back.has_accelerations.any()
    both = concatenate([back, back])
    assert both.worlds.tolist() == [4, 1, 4, 1] and both.offsets.tolist() == [0, 2, 3, 5, 6]
    np.testing.assert_array_equal(both.positions[3:], batch.positions)


def test_reset_requests_carry_their_worlds():
    assert decode_reset(np.frombuffer(encode_reset(5, None), np.uint8)) == (5, None)
    ticket, worlds = decode_reset(np.frombuffer(encode_reset(6, [3, 9]), np.uint8))
    assert ticket == 6 and worlds.tolist() == [3, 9]
    assert Kind.TRAJECTORY == 1


# --- options, rates, the plan ---
def test_one_rate_check_for_control_publish_and_update_rates():
    assert whole_ratio(1000.0, 100.0) == 10
    with pytest.raises(RateError) as e:
        whole_ratio(100.0, 30.0)
    assert e.value.nearest == pytest.approx(33.333333) and e.value.hint == "try 33.3333 Hz"
    sim = batchsim.make("arm", 1, "cpu")
    with pytest.raises(OptionError) as e:
        SimLoop(sim, control_rate=300)
    assert e.value.option == "control_rate" and "--" not in str(e.value)
    assert e.value.named("--control-rate").startswith("--control-rate 300 Hz is not a whole number of physics steps")
    with pytest.raises(OptionError) as e:
        BridgeOptions(publish_rate=30).decimation("publish_rate", 100.0)
    assert str(e.value) == "publish_rate 30 Hz must divide the control rate 100 Hz (try 33.3333 Hz)"
    assert BridgeOptions(publish_rate=25).decimation("sensor_rate", 100.0) == 4  # follows the publish rate


def test_default_workers_grow_with_the_fleet_and_the_cores():
    assert default_workers(16, cores=16) == 0
    assert default_workers(1024, cores=2) == 1  # publishing beside the physics, not in its way
    assert default_workers(16, cores=2) == 1
    assert default_workers(16, cores=1) == 0
    assert default_workers(256, cores=16) == 2
    assert default_workers(1024, cores=16) == 8
    assert default_workers(8192, cores=16) == 8
    assert split_worlds(10, 3) == [range(0, 3), range(3, 7), range(7, 10)]
    sim = batchsim.make("arm", 2, "cpu")  # more workers than worlds: one world each
    sim.configure()
    assert build_plan(sim, 100.0, BridgeOptions(), None, 5)[0].ranges == [(0, 1), (1, 2)]
    sim.shutdown()


def test_every_enum_taken_from_a_string_takes_any_case():
    """One lookup (batchsim.types.AnyCase, issue 22), by value or name, in every enum a string
    names at an edge; unknown strings and numbers are still refused."""
    from batchsim.backends import Backend
    from batchsim.controllers.manager import Strictness
    from batchsim.pid import AntiWindup
    from ros_bridge.options import Reliability

    assert AntiWindup("Back_Calculation") is AntiWindup.BACK_CALCULATION
    assert Reliability("BEST_EFFORT") is Reliability.BEST_EFFORT and Backend("Warp") is Backend.WARP
    assert Strictness("strict") is Strictness.STRICT and Strictness(4) is Strictness.BEST_EFFORT
    for enum_type, value in ((AntiWindup, "backcalc"), (Reliability, 1), (Strictness, "auto"), (Strictness, 7)):
        with pytest.raises(ValueError):
            enum_type(value)


def test_fleet_conflicts_carry_a_kind_from_the_registry_or_a_workers_status_line(tmp_path):
    """The registry names what another live fleet serves as a ConflictKind; a worker's status
    line (`conflict clock ...`) gives it by value, and FleetConflict turns it into the member."""
    from ros_bridge.registry import ConflictKind, Registry
    from ros_bridge.supervisor import FleetConflict

    first, second = Registry(tmp_path / "domain_0"), Registry(tmp_path / "domain_0")
    assert first.claim("batchsim_0_1", ["world_0", "world_1"], clock=True) is None
    try:
        kind, message = second.claim("batchsim_1_2", ["world_1", "world_2"], clock=False)
        assert kind is ConflictKind.NAMESPACE and "already serves /world_1 " in message
        kind, message = second.claim("batchsim_2_3", ["world_2"], clock=True)
        assert kind is ConflictKind.CLOCK and "already publishes /clock" in message
    finally:
        first.release()
    assert FleetConflict(ConflictKind.NAMESPACE, "m").kind is ConflictKind.NAMESPACE
    assert FleetConflict("clock", "m").kind is ConflictKind.CLOCK and str(FleetConflict("clock", "m")) == "m"
    with pytest.raises(ValueError):
        FleetConflict("topics", "m")


def test_plan_of_the_arm_with_its_controllers():
    sim = batchsim.make("arm", 8, "cpu")
    sim.configure()
    manager = load_controllers(default_controllers("arm"), sim.spec, 8)
    plan, fills, inputs = build_plan(sim, 100.0, BridgeOptions(publish_rate=50, world_offset=100), manager, 3)
    assert plan.namespaces[0] == "world_100" and plan.node_names == ["batchsim_100_102", "batchsim_103_104", "batchsim_105_107"]
    topics = {o.topic: o for o in plan.outputs}
    # the broadcaster's joint_states replace the bridge's own: one joint_states output
    assert [o.topic for o in plan.outputs].count("joint_states") == 1
    assert not topics["joint_states"].on_request and topics["joint_states"].every == 2
    assert topics["sensors/wrist_force"].on_request and topics["sensors/wrist_force"].msg_type == "std_msgs/msg/Float64MultiArray"
    assert topics["joint_trajectory_controller/controller_state/error"].on_request
    assert not topics["wrist_ft_broadcaster/wrench"].on_request
    # a site with force and torque sensors (Sensor.type, mujoco.mjtSensor) publishes a wrench
    assert [f.name for f in topics["sensors/wrist/wrench"].fields] == ["force", "torque"]
    assert set(plan.owners) == {"joint_trajectory_controller"}
    assert [i.topic for i in plan.inputs] == ["joint_trajectory_controller/joint_trajectory"]
    assert len(inputs) == 1 and len(fills) == len(plan.channels)
    for c, fill in enumerate(fills):  # every channel fills from the live arrays
        out = np.full((8, plan.channels[c].width), -7.0)
        fill(out)
        assert not (out == -7.0).all(), plan.channels[c].name
    with pytest.raises(OptionError, match="qos_depth must be >= 1"):
        build_plan(sim, 100.0, BridgeOptions(qos_depth=0), manager, 1)


def test_a_remote_endpoint_with_another_definition_is_named_once():
    """ros_bridge/worker/type_check.py on a stand-in graph: a subscriber of /tf whose
    TFMessage hash differs from batchsim's own gets one line naming both; a matching one,
    a topic of another package and an unchanged graph get none."""
    import types

    from ros_bridge.worker.type_check import TypeCheck

    def info(node: str, gid: int, digest: str, type_name: str = "tf2_msgs/msg/TFMessage"):
        return types.SimpleNamespace(
            node_name=node, node_namespace="/", endpoint_gid=[gid] * 16, topic_type=type_name, topic_type_hash=digest
        )

    class Graph:
        def __init__(self):
            self.pubs = {"/tf": [info("batchsim_0_3", 1, "RIHS01_aa")]}
            self.subs = {"/tf": [info("rviz", 2, "RIHS01_aa"), info("old_rviz", 3, "RIHS01_bb")]}
            self.errors: list[str] = []

        def get_logger(self):
            return types.SimpleNamespace(error=self.errors.append)

        def get_name(self):
            return "batchsim_0_3"

        def get_namespace(self):
            return "/"

        def count_publishers(self, topic):
            return len(self.pubs.get(topic, []))

        def count_subscribers(self, topic):
            return len(self.subs.get(topic, []))

        def get_publishers_info_by_topic(self, topic):
            return list(self.pubs.get(topic, []))

        def get_subscriptions_info_by_topic(self, topic):
            return list(self.subs.get(topic, []))

    graph = Graph()
    check = TypeCheck(graph)
    topics = [("/tf", ["tf2_msgs/msg/TFMessage"]), ("/world_0/joint_states", ["sensor_msgs/msg/JointState"])]
    check.scan(topics)
    assert len(graph.errors) == 1
    line = graph.errors[0]
    assert "/tf: node /old_rviz" in line and "tf2_msgs/msg/TFMessage" in line and "RIHS01_bb" in line and "RIHS01_aa" in line
    check.scan(topics)  # nothing changed: nothing looked at again
    graph.subs["/tf"].append(info("late", 4, "RIHS01_aa"))
    check.scan(topics)
    assert len(graph.errors) == 1
    # a worker looks only at its own topics, a bounded number per scan (thousands of action
    # servers' topics counted every second kept an H100 host's workers from publishing)
    import ros_bridge.worker.type_check as tc

    counted: list[str] = []
    graph.count_publishers = lambda topic: counted.append(topic) or 0
    many = [(f"/world_{w}/tf", ["tf2_msgs/msg/TFMessage"]) for w in range(100)]
    mine = TypeCheck(graph, ("/world_1/", "/world_2/", "/tf"))
    mine.scan(many + topics)
    assert sorted(counted) == ["/tf", "/world_1/tf", "/world_2/tf"]
    counted.clear()
    TypeCheck(graph).scan(many)
    assert len(counted) == tc.PER_SCAN


def test_a_hung_worker_is_killed_and_restarted(monkeypatch):
    """The supervisor's watch over a live worker's tick counter: silent HUNG_AFTER s -> reported
    (and `worker.hung` set for the others' /diagnostics); silent HUNG_RESTART s -> killed, so the
    next look restarts it as one that died; ticking again -> said so, the flag cleared."""
    import ros_bridge.supervisor as sv
    from batchsim.memory import Layout, Memory

    class FakePopen:
        pid, killed = 4242, False

        def kill(self):
            self.killed = True

    lines: list[str] = []

    class Throttle:
        def warn(self, key, line):
            lines.append(line)

    memory = Memory.create(Layout([("beat", (2,), "i8"), ("worker.hung", (2,), "f8")]), shared=False)
    supervisor = sv.Supervisor.__new__(sv.Supervisor)
    supervisor.memory, supervisor.throttle = memory, Throttle()
    supervisor.plan = type("Plan", (), {"ranges": [(0, 2), (2, 4)], "namespaces": [f"world_{i}" for i in range(4)]})()
    p = sv._Process.__new__(sv._Process)
    p.popen, p.beat, p.beat_at, p.hung_since = FakePopen(), 7, 100.0, 0.0
    memory["beat"][1] = 7
    supervisor._watch(1, p, 100.5)
    assert not lines
    supervisor._watch(1, p, 100.0 + sv.HUNG_AFTER)
    assert "bridge worker 1 (pid 4242) has not answered for 1.0 s (busy or hung): /world_2 .. /world_3" in lines[-1]
    assert memory["worker.hung"][1] > 0 and not p.popen.killed
    memory["beat"][1] = 8  # it ticks again
    supervisor._watch(1, p, 102.0)
    assert lines[-1] == "bridge worker 1 answers again" and memory["worker.hung"][1] == 0
    supervisor._watch(1, p, 102.0 + sv.HUNG_AFTER)
    supervisor._watch(1, p, 102.0 + sv.HUNG_RESTART)
    assert p.popen.killed and "did not answer for 30 s: killed" in lines[-1]
    memory.close()


def test_a_second_step_simulation_waits_for_the_first_and_each_is_answered_when_its_steps_ran():
    """mujoco_ros2_control serializes step_simulation (a mutually exclusive callback group): a
    second request runs after the first, and the first is answered when its own steps ran."""
    import threading

    from ros_bridge.simulation import SimulationRequests

    sim = batchsim.make("arm", 1, "cpu")
    sim.configure()
    sim.activate()
    loop = SimLoop(sim, control_rate=100.0, rtf=0.0)
    answers: list[tuple[int, float, bool, str]] = []
    requests = SimulationRequests(sim, loop, lambda w, t, time, ok, msg: answers.append((t, time, ok, msg)))

    class Poll:  # as the bridge host polls: every period and while paused
        def update(self, sim, t, period):
            requests.poll()

        def idle(self, sim, t):
            requests.poll()

    loop.participants.append(Poll())
    loop.pause(True)
    requests.step(0, 1, 7)
    requests.step(0, 2, 25)
    runner = threading.Thread(target=loop.run)
    runner.start()
    try:
        deadline = time.monotonic() + 30
        while len(answers) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        loop.stop()
        runner.join()
        sim.shutdown()
    dt = sim.dt
    assert [(t, ok, msg) for t, _, ok, msg in answers] == [
        (1, True, "Completed 7 simulation step(s)."), (2, True, "Completed 25 simulation step(s)."),
    ]  # fmt: skip
    assert answers[0][1] == pytest.approx(7 * dt) and answers[1][1] == pytest.approx(32 * dt)


def test_a_worker_with_many_worlds_gets_longer_to_start():
    """One worker took 104 s to create the endpoints of 4096 arms on the idle 2-core VM (6.5 s
    for 1024, 20.6 s for 2048) and over the fixed 120 s under load: `batchsim --worlds 4096`
    failed with 'did not start in 120 s'. The wait grows with the square of its worlds."""
    from ros_bridge.supervisor import START_TIMEOUT, start_timeout

    assert start_timeout(16) == start_timeout(2048) == START_TIMEOUT == 120.0
    assert start_timeout(4096) == 4 * START_TIMEOUT
    assert start_timeout(8192) == 16 * START_TIMEOUT


def test_a_step_run_while_paused_is_published_as_it_left_the_worlds():
    """While paused, a step (the step services) ran read, the controllers, write and the
    physics; the bridge then published it under the new sim time, but with what read() had
    filled before the physics ran: the state of the period before."""
    from ros_bridge.host import BridgeHost
    from ros_bridge.protocol.snapshot import Snapshot, read_snapshot

    sim = batchsim.make("arm", 2, "cpu")
    sim.configure()
    sim.activate()
    loop = SimLoop(sim, control_rate=100.0, rtf=0.0)  # no controllers: the commands below move the arm
    plan, fills, inputs = build_plan(sim, loop.control_rate, BridgeOptions(), None, 1)
    host = BridgeHost(sim, loop, plan, fills, inputs, processes=False)
    host.attach()
    joint_states = next(o for o in plan.outputs if o.topic == "joint_states")
    position = next(f for f in joint_states.fields if f.name == "position")
    column = {name: i for i, name in enumerate(sim.spec.state_interfaces)}
    host.memory["demand"][:, position.channel] = 1
    try:
        sim.command[:] = 1.5
        loop.run_period()
        loop.run_period()  # as a paused loop runs a step it was asked for
        host.idle(sim, loop.sim_time)  # then idles, paused
        snap = read_snapshot(host.memory, len(plan.channels), 0, sim.nworld, Snapshot())
        assert snap.time == pytest.approx(loop.sim_time)
        sim.read()
        expected = sim.state[:, [column[f"{j}/position"] for j in joint_states.names]]
        np.testing.assert_array_equal(snap.channels[position.channel][:, list(position.columns)], expected)
    finally:
        host.close()
        sim.shutdown()


def test_controller_nodes_auto_is_on_for_small_fleets_and_the_root_namespace():
    from ros_bridge.options import CONTROLLER_NODES_UP_TO, ControllerNodes

    small = [f"world_{i}" for i in range(CONTROLLER_NODES_UP_TO)]
    large = [f"world_{i}" for i in range(CONTROLLER_NODES_UP_TO + 1)]
    assert ControllerNodes("auto").wanted(small) and not ControllerNodes("AUTO").wanted(large)
    assert ControllerNodes.AUTO.wanted([""])  # one world at the root: a ros2_control robot's drop-in
    assert ControllerNodes("on").wanted(large) and not ControllerNodes("off").wanted([""])


def test_a_worlds_requests_have_a_budget_and_its_neighbours_keep_theirs():
    """A flood of switch_controller calls on one world held every other world's services behind
    it (issue 47's review: p50 6 ms -> 555 ms): each world has a budget (a token bucket)."""
    import threading

    from ros_bridge.protocol.services import service_arrays
    from ros_bridge.worker.services import GOAL_RATE, WORLD_RATE, LoopRequests

    memory = Memory.create(Layout(service_arrays(1) + ring_arrays("ring0", 4096)), shared=False)
    requests = LoopRequests(memory, 0, Ring(memory, "ring0"), threading.Lock(), lambda: None)
    flood = [requests.admit(3, now=10.0) for _ in range(100)]  # 100 at once from world 3
    assert sum(flood) == WORLD_RATE and flood[: int(WORLD_RATE)] == [True] * int(WORLD_RATE)
    assert requests.admit(0, now=10.0)  # its neighbour's first goes through
    assert not requests.admit(3, now=10.02) and requests.admit(3, now=10.06)  # 20 a second come back
    assert sum(requests.admit(3, now=11.5 + k * 0.01) for k in range(10)) == 10  # a calm world: all
    assert sum(requests.admit(5, now=10.0, rate=GOAL_RATE) for _ in range(150)) == GOAL_RATE  # goals: their own
    message, log = requests.refusal("/world_3/controller_manager/switch_controller", now=10.0)
    assert log and not requests.refusal("/world_3/controller_manager/switch_controller", now=11.0)[1]
    assert message.startswith("/world_3/controller_manager/switch_controller: more requests a second")

