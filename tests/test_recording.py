"""MCAP recording and replay (issue 25), with the real components: a `batchsim --record` process
writes the file, mcap's reader and mcap-ros2-support's decoder read it back, `batchsim replay`
republishes it to a subscriber in this process, each on its own ROS domain; a recorder killed
outright leaves a readable file and the fleet running; bad input is one line."""

from __future__ import annotations

import os
import signal
import time
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pytest
from conftest import need
from ros_fleet import (
    LOCALHOST,
    alive,
    batchsim_process,
    children,
    cmdline,
    domain_id,
    release_domain,
    spin_until_exit,
)

rclpy = need("rclpy")
need("mcap")
need("mcap_ros2")

from mcap.reader import NonSeekingReader, make_reader  # noqa: E402
from mcap.stream_reader import StreamReader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402

from batchsim import cli  # noqa: E402
from ros_bridge.worker.schemas import DELIMITER, schema_text  # noqa: E402

pytestmark = pytest.mark.ros
NWORLD, DURATION, RATE = 3, 1.0, 100  # the recorded run: 100 control periods


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    """Worlds 0 and 2 of 3 arms, 1 s of sim time as fast as the recorder takes it."""
    where = tmp_path_factory.mktemp("recording")
    path = where / "run.mcap"
    domain = domain_id(70)
    try:
        args = ["--worlds", str(NWORLD), "--rtf", "0", "--duration", str(DURATION), "--quiet", "--record", str(path)]
        proc = batchsim_process([*args, "--record-worlds", "0,2"], domain, where / "log")
        assert proc.wait(timeout=120) == 0, (where / "log").read_text()
    finally:
        release_domain(domain)
    assert f"messages in {path}" in (where / "log").read_text()
    return path


def test_a_recording_reads_back_with_mcap_and_its_ros2_decoder(recorded):
    with open(recorded, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        header, summary = reader.get_header(), reader.get_summary()
        assert header.profile == "ros2"
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        assert all("offered_qos_profiles" in c.metadata for c in summary.channels.values())
        assert summary.chunk_indexes and {c.compression for c in summary.chunk_indexes} == {"zstd"}
        counts: Counter[str] = Counter()
        times: dict[str, list[int]] = defaultdict(list)
        status: list[tuple[int, dict]] = []
        for _schema, channel, message, decoded in reader.iter_decoded_messages():  # every schema decodes
            counts[channel.topic] += 1
            times[channel.topic].append(message.log_time)
            stamp = getattr(getattr(decoded, "header", None), "stamp", None) or getattr(decoded, "clock", None)
            if stamp is not None:
                assert stamp.sec * 10**9 + stamp.nanosec == message.log_time, channel.topic  # stamps are sim time
            if channel.topic == "/tf":
                assert {t.child_frame_id.split("/")[0] for t in decoded.transforms} == {"world_0", "world_2"}
            if channel.topic == "/diagnostics":
                status.append((message.log_time, {s.hardware_id: (s.name, s.message) for s in decoded.status}))
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert summary.statistics.message_count == sum(counts.values())
    periods = round(DURATION * RATE)
    for world in (0, 2):  # every recorded world's every period, in order
        topic = f"/world_{world}/joint_states"
        assert counts[topic] == periods
        assert times[topic] == sorted(set(times[topic]))
        assert times[topic] == times["/clock"]
        assert counts[f"/world_{world}/robot_description"] == 1
    assert not any(t.startswith("/world_1/") for t in counts)  # --record-worlds 0,2
    assert counts["/tf"] == periods and counts["/tf_static"] == 1
    assert metadata["batchsim"]["worlds"] == "[0, 2]"
    # the worlds' status: every recorded world at the first period (and once a sim second)
    assert status[0] == (times["/clock"][0], {f"world_{w}": (f"batchsim: world_{w}", "ok") for w in (0, 2)})
    assert 1 <= len(status) <= 2


def test_a_recordings_status_holds_each_change_and_the_view_reads_it_back():
    """/diagnostics in a recording: every world at first and once a sim second, in between the
    worlds that changed, in the period they changed; the view's reading gives each world's
    status at each time (ros_bridge/view_file.py)."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.serialization import deserialize_message

    from batchsim.types import Status
    from ros_bridge.plan import FLAG_BAD, FLAG_FROZEN
    from ros_bridge.view_file import Recording as ViewRecording
    from ros_bridge.worker.status_recording import StatusRecording
    from ros_bridge.world_status import from_values, status_text

    namespaces = ["world_0", "world_1", "world_2"]
    rec = StatusRecording(namespaces)
    ok = np.zeros(3, np.uint8)
    bad = np.array([0, int(Status.BAD_COMMAND), 0], np.uint8)
    frozen = np.array([0, 0, int(Status.DIVERGED)], np.uint8)
    written = []
    for t, bits, flags in [
        (0.01, ok, ok),
        (0.02, ok, ok),
        (0.03, bad, np.array([0, FLAG_BAD, 0], np.uint8)),
        (0.04, bad, np.array([0, FLAG_BAD, 0], np.uint8)),
        (0.05, bad | frozen, np.array([0, FLAG_BAD, FLAG_FROZEN], np.uint8)),
        (1.00, bad | frozen, np.array([0, FLAG_BAD, FLAG_FROZEN], np.uint8)),
    ]:
        data = rec.message(t, 0, int(t * 1e9), bits, flags)
        if data is not None:
            msg = deserialize_message(data, DiagnosticArray)
            written.append((t, [(s.hardware_id, *from_values({v.key: v.value for v in s.values}), s.message) for s in msg.status]))
            levels = {s.hardware_id: s.level for s in msg.status}
            if "world_2" in levels:  # ERROR once diverged
                assert levels["world_2"] == (b"\x02" if t >= 0.05 else b"\x00")
    assert [t for t, _ in written] == [0.01, 0.03, 0.05, 1.00]
    assert [len(s) for _, s in written] == [3, 1, 1, 3]
    assert written[1][1] == [("world_1", int(Status.BAD_COMMAND), FLAG_BAD, "bad_command")]
    assert written[2][1][0][:3] == ("world_2", int(Status.DIVERGED), FLAG_FROZEN)
    assert written[2][1][0][3] == "diverged (frozen until reset: its state topics stopped)"
    view = ViewRecording.__new__(ViewRecording)  # only its status reading, on kept frame times
    view.namespaces, view.times = namespaces, np.array([0.01, 0.02, 0.04, 0.06, 1.0])
    bits, flags = view._status_at([(int(t * 1e9), [(ns, b, f) for ns, b, f, _ in s]) for t, s in written])
    assert [status_text(int(b), int(f)) for b, f in zip(bits[:, 1], flags[:, 1], strict=True)] == [
        "running", "running", "bad command", "bad command", "bad command"
    ]
    assert [status_text(int(b), int(f)) for b, f in zip(bits[:, 2], flags[:, 2], strict=True)] == [
        "running", "running", "running", "frozen (diverged) until reset", "frozen (diverged) until reset"
    ]


def test_a_recordings_status_holds_the_live_counts_and_last_problem_of_bad_commands():
    """Before, the recorded /diagnostics lacked what the live one says of rejected commands
    (issue 47): their count and the last one's reason, read from the bridge's shared memory,
    the bridge workers' (`rej`) and the loop's controllers' (`hrej`); a new rejection is a change."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.serialization import deserialize_message

    from batchsim.memory import Layout, Memory
    from batchsim.types import Status
    from ros_bridge.plan import FLAG_BAD
    from ros_bridge.protocol.commands import RejectionWriter, rejection_arrays
    from ros_bridge.worker.status_recording import StatusRecording

    memory = Memory.create(Layout(rejection_arrays("rej", 3) + rejection_arrays("hrej", 3)), shared=False)
    mine, host = RejectionWriter(memory, "rej"), RejectionWriter(memory, "hrej")
    rec = StatusRecording(["world_0", "world_2"], (mine, host, [0, 2]))  # worlds 0 and 2 of 3 recorded
    ok, bad = np.zeros(2, np.uint8), np.array([0, int(Status.BAD_COMMAND)], np.uint8)
    flags = np.array([0, FLAG_BAD], np.uint8)

    def statuses(t, bits, fl):
        data = rec.message(t, 0, int(t * 1e9), bits, fl)
        if data is None:
            return None
        return {s.hardware_id: (s.message, {v.key: v.value for v in s.values}) for s in deserialize_message(data, DiagnosticArray).status}

    assert statuses(0.01, ok, ok)["world_2"][1]["bad_commands"] == "0"
    mine.put(2, 3, "/world_2/commands", "value nan at index 1")
    first = statuses(0.03, bad, flags)
    assert list(first) == ["world_2"]
    assert first["world_2"][0] == "bad_command (/world_2/commands: value nan at index 1)"
    assert first["world_2"][1]["bad_commands"] == "1" and first["world_2"][1]["last_problem"] == "/world_2/commands: value nan at index 1"
    host.put(2, 4, "/world_2/joint_trajectory", "2 points for 6 joints")  # the loop's, later: the last
    second = statuses(0.04, bad, flags)  # the same bits and flags: a new rejection is a change
    assert second["world_2"][1]["bad_commands"] == "2"
    assert second["world_2"][1]["last_problem"] == "/world_2/joint_trajectory: 2 points for 6 joints"
    assert statuses(0.05, bad, flags) is None


def test_schemas_carry_their_dependencies_as_rosbag2_writes_them():
    text = schema_text("sensor_msgs/msg/JointState")
    assert text.startswith("#") or text.startswith("std_msgs/Header")
    assert f"\n{DELIMITER}\nMSG: std_msgs/msg/Header\n" in text
    assert f"\n{DELIMITER}\nMSG: builtin_interfaces/msg/Time\n" in text
    assert text.count("MSG: ") == 2


def test_replay_republishes_what_was_recorded(recorded, tmp_path):
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import JointState

    with open(recorded, "rb") as f:
        reader = make_reader(f)
        expected = [m.data for _s, c, m in reader.iter_messages(topics=["/world_2/joint_states"])]
    domain = domain_id(70)
    os.environ.update(LOCALHOST)
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    node = Node("test_replay_client", context=context)
    from diagnostic_msgs.msg import DiagnosticArray

    got: list[bytes] = []
    clock: list[bytes] = []
    diagnostics: list = []
    node.create_subscription(JointState, "/world_2/joint_states", got.append, QoSProfile(depth=1000), raw=True)
    node.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, QoSProfile(depth=1000))
    node.create_subscription(Clock, "/clock", clock.append, QoSProfile(depth=1000), raw=True)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    proc = batchsim_process(["replay", str(recorded), "--worlds", "2", "--rate", "2", "--delay", "5"], domain, tmp_path / "log")
    try:
        spin_until_exit(executor, proc)
        log = (tmp_path / "log").read_text()
        assert proc.returncode == 0, log
        assert got == expected, log  # the recorded CDR bytes, every one, in order
        assert len(clock) == len(expected)
        assert node.count_publishers("/world_0/joint_states") == 0
        # /diagnostics goes out with world 2's statuses only (before: not at all under --worlds)
        assert diagnostics and {s.hardware_id for d in diagnostics for s in d.status} == {"world_2"}
    finally:
        if proc.poll() is None:
            proc.kill()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        release_domain(domain)


def _messages_until_cut(path: Path) -> int:
    """Messages a streaming reader gets out of a file cut short, up to its last complete chunk."""
    n = 0
    if not path.exists():
        return 0
    with open(path, "rb") as f:
        try:
            for _ in NonSeekingReader(f).iter_messages(log_time_order=False):
                n += 1
        except Exception:  # the cut: a record that never ended
            pass
    return n


def test_a_killed_recorder_leaves_a_readable_file_and_the_fleet_running_and_the_service_records_again(tmp_path):
    from std_srvs.srv import SetBool

    path = tmp_path / "live.mcap"
    domain = domain_id(70)
    proc = batchsim_process(["--worlds", "2", "--quiet", "--controllers", "none", "--record", str(path)], domain, tmp_path / "log")
    log = tmp_path / "log"
    os.environ.update(LOCALHOST)
    context = None
    try:
        deadline = time.monotonic() + 60
        recorder = None
        while recorder is None or _messages_until_cut(path) < 100:  # a second's chunks on disk
            assert proc.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.2)
            recorder = next((c for c in children(proc.pid) if "ros_bridge.worker.recorder" in cmdline(c)), None)
        os.kill(recorder, signal.SIGKILL)
        while "was killed by signal 9" not in log.read_text():
            assert time.monotonic() < deadline, log.read_text()
            time.sleep(0.1)
        assert alive(proc.pid)  # the simulation goes on
        n = _messages_until_cut(path)
        assert n >= 100
        # ... and a recording started through the service, stopped through it, is complete
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        context = Context()
        rclpy.init(context=context, domain_id=domain)
        node = Node("test_record_client", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        client = node.create_client(SetBool, "/batchsim/record")
        assert client.wait_for_service(timeout_sec=30)

        def call(on: bool):
            future = client.call_async(SetBool.Request(data=on))
            executor.spin_until_future_complete(future, timeout_sec=10)
            return future.result()

        (tmp_path / "live_2.mcap").write_bytes(b"an earlier run's")  # never recorded over: the next number
        started = call(True)
        assert started.success and started.message == f"recording to {tmp_path / 'live_3.mcap'}", started.message
        assert not call(True).success  # already recording
        time.sleep(3.0)  # issue 46: a 3 s recording by service held 0 messages, a 15 s one its last 11.2 s
        stopped = call(False)
        assert stopped.success, stopped.message
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0, log.read_text()
        assert (tmp_path / "live_2.mcap").read_bytes() == b"an earlier run's"
        with open(tmp_path / "live_3.mcap", "rb") as f:
            summary = make_reader(f).get_summary()
        assert summary.statistics.message_count > 0
        span = (summary.statistics.message_end_time - summary.statistics.message_start_time) * 1e-9
        assert span >= 2.5, span  # the 3 s between the calls (rtf 1, 2 arms), none lost to the recorder's start
    finally:
        if proc.poll() is None:
            proc.kill()
        if context is not None:
            rclpy.try_shutdown(context=context)
        release_domain(domain)


def test_a_full_disk_stops_the_recording_with_one_line_and_the_run_goes_on(tmp_path):
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full")
    domain = domain_id(70)
    try:
        proc = batchsim_process(["--worlds", "1", "--rtf", "0", "--duration", "0.5", "--record", "/dev/full"], domain, tmp_path / "log")
        assert proc.wait(timeout=120) == 0
    finally:
        release_domain(domain)
    lines = (tmp_path / "log").read_text().splitlines()
    assert "batchsim: warning: recording stopped: /dev/full: No space left on device; the simulation goes on" in lines
    assert any(line.startswith("batchsim: stopped at sim time 0.500 s") for line in lines)


@pytest.mark.parametrize(
    "args, line",
    [
        (["--record", "/nonexistent/run.mcap"], "--record /nonexistent/run.mcap: directory /nonexistent does not exist"),
        (["--record", "."], "--record . is a directory"),
        (["--record", "README.md"], "--record README.md exists; batchsim never records over a file (remove it, or name another)"),
        (["--record-topics", "joint_states,bogus"], "--record-topics names 'bogus', which this fleet does not publish"),
        (["--record-worlds", "1,7"], "--record-worlds names world 7, which this fleet does not have (worlds 0..1)"),
        (["--record-topics", "image_raw"], "--record-topics names 'image_raw', which this fleet does not publish"),
        (["--view"], "--view draws the robots from tf's body poses: it needs tf (drop --no-tf)"),
        (["--view", "--view-host", "10.99.99.99"], "--view-host 10.99.99.99: cannot serve there"),
    ],
)
def test_what_cannot_be_recorded_or_viewed_is_one_line(args, line, capsys, monkeypatch):
    domain = domain_id(70)
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    try:
        assert cli.main(["--worlds", "2", "--controllers", "none", "--no-tf", *args]) == 2
    finally:
        release_domain(domain)
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"batchsim: error: {line}"), err


def test_a_fleet_that_does_not_fit_in_dev_shm_is_one_line(capsys, monkeypatch):
    from conftest import fake_shm_free

    domain = domain_id(70)
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    fake_shm_free(monkeypatch, 4096)
    try:
        assert cli.main(["--worlds", "2", "--controllers", "none", "--duration", "0.1"]) == 2
    finally:
        release_domain(domain)
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("batchsim: error: shared memory: this fleet needs"), err


def test_what_cannot_be_replayed_or_viewed_is_one_line(recorded, tmp_path, capsys):
    text = tmp_path / "notes.txt"
    text.write_text("not a recording\n")
    assert cli.main(["replay", str(text)]) == 2
    assert capsys.readouterr().err.strip() == f"batchsim: error: {text} is not an MCAP file (it does not start with MCAP's magic bytes)"
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(recorded.read_bytes()[:400])  # the header and the metadata, no chunk
    assert cli.main(["replay", str(cut)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == f"batchsim: error: {cut} was cut short before its first complete chunk: nothing to replay"
    assert err[0].startswith(f"batchsim: warning: {cut} was cut short")
    assert cli.main(["view", str(text)]) == 2
    assert capsys.readouterr().err.strip() == f"batchsim: error: {text} is not an MCAP file (it does not start with MCAP's magic bytes)"
    assert cli.main(["replay", str(recorded), "--worlds", "1"]) == 2
    assert capsys.readouterr().err.strip() == f"batchsim: error: --worlds names world 1, which {recorded} does not hold (worlds [0, 2])"
    assert sum(1 for _ in StreamReader(str(recorded)).records) > 0


def test_a_recording_cut_anywhere_is_read_up_to_the_cut_or_refused_in_one_line(recorded, tmp_path):
    """Before, `batchsim view` on a file cut inside a record's header died of a struct.error
    traceback (issue 47's review): every cut, a few bytes in or anywhere in its chunks."""
    from ros_bridge.recording_file import ReplayError
    from ros_bridge.view_file import Recording

    data = recorded.read_bytes()
    cut = tmp_path / "cut.mcap"
    read = 0
    for n in sorted({9, 12, 17, 20, 30, *range(64, len(data), max(1, len(data) // 40))}):
        cut.write_bytes(data[:n])
        said = []
        try:
            recording = Recording(str(cut), said.append)
            read += 1
            assert recording.namespaces
        except ReplayError as e:
            assert "\n" not in str(e) and str(cut) in str(e), e
        assert said and "was cut short" in said[0]
    assert read > 10  # the chunks before each cut


def test_the_view_opens_a_recording_through_its_index_and_decodes_a_frame_when_shown(recorded, monkeypatch):
    """Issue 46: `batchsim view` decoded every /tf and joint_states message and composed every
    world's poses in a Python loop before its URL line (9 minutes for 256 worlds, 46 MB). Now
    opening decodes /tf_static, /diagnostics and one joint_states only; a frame's /tf is decoded
    when it is shown, and a world's joint_states when it is picked, and they give what the
    stream read (the path of a file cut short) gives."""
    from ros_bridge.view_file import Recording

    decoded: Counter[str] = Counter()
    decode = Recording._decode

    def counting(self, channel, schema, data):
        decoded[channel.topic] += 1
        return decode(self, channel, schema, data)

    monkeypatch.setattr(Recording, "_decode", counting)
    rec = Recording(str(recorded), lambda line: None)
    try:
        assert decoded["/tf"] == 0 and sum(n for t, n in decoded.items() if t.endswith("/joint_states")) == 1
        assert len(rec.times) > 10
        k = len(rec.times) // 2
        shown = rec.transforms(k)
        assert decoded["/tf"] == 1  # that frame's message alone
        stream = Recording(str(recorded), lambda line: None)
        stream._file = None
        times = stream._read_stream(str(recorded), True, [])
        assert np.allclose(np.array(times) * 1e-9, rec.times)
        assert shown.keys() == stream._moving[k].keys()
        for name, (parent, pose) in shown.items():
            assert stream._moving[k][name][0] == parent and np.allclose(stream._moving[k][name][1], pose)
        t, q = rec.joint_series(0, float(rec.times[-1]))
        stream_t, stream_q = stream.joint_series(0, float(rec.times[-1]))
        assert len(t) and q.shape[1] == 6 and np.isin(np.round(t, 6), np.round(stream_t, 6)).all()
        poses = rec.anchor_poses(k, ["link1", "link6"], [0, 1])
        assert poses.shape == (2, 2, 7) and np.allclose(np.linalg.norm(poses[..., 3:], axis=-1), 1.0)
        stream.close()
    finally:
        rec.close()
