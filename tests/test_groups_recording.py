"""A fleet of two groups of worlds recorded, replayed and viewed as one (ros_bridge/bridge.py's
join_bridges): `batchsim --fleet ... --record` writes one MCAP file of both groups' worlds under
their fleet namespaces, one /clock; `batchsim replay` republishes both groups' topics over DDS;
`batchsim view FILE` draws each world with its own group's robots. Real components: the
`batchsim` process, its bridges, its recorder; mcap's reader and mcap-ros2-support's decoder.

The fleet: group `arms`, 2 worlds of an arm (worlds 0 and 1), and group `yard`, 2 worlds of an
arm beside a rover (worlds 2 and 3), as tests/test_groups_ros.py's.
"""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import time
from collections import Counter, defaultdict
from pathlib import Path

import pytest
from conftest import need
from depot import DEPOT
from ros_fleet import LOCALHOST, Fleet, batchsim_process, domain_id, release_domain, spin_until_exit

rclpy = need("rclpy")
need("mcap")
need("mcap_ros2")
need("viser")

import yaml  # noqa: E402
from mcap.reader import NonSeekingReader, make_reader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402
from view_clients import connect, wait  # noqa: E402

from batchsim import cli  # noqa: E402

pytestmark = pytest.mark.ros
DURATION, RATE = 1.0, 100  # the recorded run: 100 control periods
PERIODS = round(DURATION * RATE)
ROBOTS = [(0, "arm"), (1, "arm"), (2, "arm"), (2, "rover"), (3, "arm"), (3, "rover")]  # (world, robot)


def _record(depot: Path, path: Path, domain_base: int, *more: str) -> str:
    """A 1 s run of the fleet as fast as the recorder takes it, recorded into `path`; its log."""
    log = path.with_suffix(".log")
    domain = domain_id(domain_base)
    try:
        args = ["--fleet", str(depot), "--backend", "cpu", "--controllers", "none", "--bridge-workers", "1",
                "--rtf", "0", "--duration", str(DURATION), "--quiet", "--record", str(path), *more]  # fmt: skip
        assert batchsim_process(args, domain, log).wait(timeout=180) == 0, log.read_text()
    finally:
        release_domain(domain)
    return log.read_text()


@pytest.fixture(scope="module")
def depot(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("depot") / "depot.yaml"
    path.write_text(yaml.safe_dump(DEPOT))
    return path


@pytest.fixture(scope="module")
def recorded(depot) -> Path:
    path = depot.parent / "run.mcap"
    log = _record(depot, path, 61)
    assert f"messages in {path}" in log
    assert not list(depot.parent.glob("run.*.mcap"))  # one file, not one per group
    return path


def _read(path: Path):
    """(summary, metadata, attachment names, per topic its messages' log times and decoded messages)."""
    times: dict[str, list[int]] = defaultdict(list)
    decoded: dict[str, list] = defaultdict(list)
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        for _schema, channel, message, msg in reader.iter_decoded_messages(log_time_order=False):
            times[channel.topic].append(message.log_time)
            decoded[channel.topic].append(msg)
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        attachments = [a.name for a in reader.iter_attachments()]
    return summary, metadata, attachments, times, decoded


def test_one_file_holds_every_groups_worlds_under_their_fleet_namespaces(recorded):
    summary, metadata, attachments, times, decoded = _read(recorded)
    topics = Counter(c.topic for c in summary.channels.values())
    assert all(n == 1 for n in topics.values()), topics  # a topic is one channel, whichever groups write it
    assert summary.statistics.message_count == sum(len(t) for t in times.values())
    clock = times["/clock"]
    assert len(clock) == PERIODS  # one /clock, from the first group
    for w, robot in ROBOTS:  # every recorded world's every period, under the fleet's numbering
        topic = f"/world_{w}/{robot}/joint_states"
        assert times[topic] == clock, topic
        stamp = decoded[topic][0].header.stamp
        assert stamp.sec * 10**9 + stamp.nanosec == times[topic][0]  # stamps are sim time
    assert list(decoded["/world_2/rover/joint_states"][0].name) == ["left_wheel_joint", "right_wheel_joint"]
    assert not any(t.startswith("/world_4/") for t in topics)
    # /tf: each group's transforms, one message per group and period, as each group's bridge publishes them
    assert len(times["/tf"]) == 2 * PERIODS
    tf_worlds = Counter(frozenset(t.child_frame_id.split("/")[0] for t in m.transforms) for m in decoded["/tf"])
    assert tf_worlds == {frozenset({"world_0", "world_1"}): PERIODS, frozenset({"world_2", "world_3"}): PERIODS}
    # /tf_static: one latched message of every group's fixed transforms
    [static] = decoded["/tf_static"]
    frames = {t.child_frame_id for t in static.transforms}
    assert {f.split("/")[0] for f in frames} == {"world_0", "world_1", "world_2", "world_3"}
    assert {"world_0/arm/base", "world_3/arm/base"} <= frames
    moving = {t.child_frame_id for m in decoded["/tf"][:2] for t in m.transforms}  # the first period's, both groups'
    assert any(f.startswith("world_3/rover/") for f in moving) and not any(f.startswith("world_1/rover/") for f in moving)
    for w in range(4):  # each world's robot_description, its own group's robots
        [description] = decoded[f"/world_{w}/robot_description"]
        assert ("rover/" in description.data) == (w >= 2), w
    # /diagnostics: every world of both groups at the first period
    first = {s.hardware_id for m, t in zip(decoded["/diagnostics"], times["/diagnostics"], strict=True) if t == clock[0] for s in m.status}
    assert first == {"world_0", "world_1", "world_2", "world_3"}
    # the metadata names every recorded world, and which are whose, with each group's geometry
    meta = metadata["batchsim"]
    assert json.loads(meta["worlds"]) == [0, 1, 2, 3]
    assert json.loads(meta["namespaces"]) == ["world_0", "world_1", "world_2", "world_3"]
    groups = json.loads(meta["groups"])
    assert [(g["name"], g["worlds"]) for g in groups] == [("arms", [0, 1]), ("yard", [2, 3])]
    geometry = sorted(a for a in attachments if "view_geometry" in a)
    assert geometry == sorted(g["geometry"] for g in groups) == ["batchsim/view_geometry.arms.npz", "batchsim/view_geometry.yard.npz"]
    # what `batchsim resim` needs, per group: its model and its inputs' topics (batchsim.resim.layout.resim_names)
    assert sorted(a for a in attachments if a.endswith(".mjb")) == ["batchsim/arms/model.mjb", "batchsim/yard/model.mjb"]
    assert len(times["/batchsim/arms/inputs"]) == len(times["/batchsim/yard/inputs"]) == PERIODS
    with open(recorded, "rb") as f:  # in sim-time order in the file: a replay paces by it
        logged = [m.log_time for _s, _c, m in NonSeekingReader(f).iter_messages(log_time_order=False)]
    assert logged == sorted(logged)


def _resim(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "batchsim.cli", "resim", *args], capture_output=True, text=True, timeout=300)


def test_every_world_of_a_fleet_of_groups_reruns_bit_exact_from_its_groups_inputs(recorded, depot, tmp_path):
    """Each group records its own inputs and model; `batchsim resim` re-runs each world from its
    group's, each robot's joint_states compared (tests/test_resim_ros.py has the rest of resim)."""
    done = _resim(str(recorded), "--tf")
    assert done.returncode == 0, done.stderr
    for w, joints in ((0, 6), (1, 6), (2, 8), (3, 8)):
        assert f"world {w}: {PERIODS * (1 if joints == 6 else 2)} joint_states compared: bit-exact (every position, velocity and effort of {joints} joints" in done.stdout, done.stdout
        assert f"world {w}: {PERIODS} /tf messages compared: bit-exact" in done.stdout, done.stdout
    assert "re-running 2 world(s) of group arms" in done.stderr and "re-running 2 world(s) of group yard" in done.stderr
    # --model names one group's model (its fleet file): the other group's worlds are refused, the group named
    arms = tmp_path / "arms.yaml"
    arms.write_text(yaml.safe_dump({"robots": DEPOT["groups"][0]["robots"]}))
    refused = _resim(str(recorded), "--model", str(arms))
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1, refused.stderr
    assert "is not the model" in refused.stderr and "(group yard, world 2)" in refused.stderr
    mine = _resim(str(recorded), "--model", str(arms), "--worlds", "0,1")
    assert mine.returncode == 0 and mine.stdout.count("bit-exact") == 2, mine.stdout + mine.stderr


def test_the_first_group_leads_where_none_of_its_worlds_is_recorded_and_a_topic_may_be_one_groups(depot, tmp_path):
    path = tmp_path / "yard.mcap"
    _record(depot, path, 61, "--record-worlds", "3", "--record-topics", "rover/joint_states,/clock")
    summary, metadata, attachments, times, _ = _read(path)
    assert sorted(t for t in times if not t.startswith("/batchsim/")) == ["/clock", "/world_3/rover/joint_states"]
    assert sorted(t for t in times if t.startswith("/batchsim/")) == ["/batchsim/yard/inputs", "/batchsim/yard/starts"]
    assert len(times["/clock"]) == PERIODS and times["/world_3/rover/joint_states"] == times["/clock"]
    assert json.loads(metadata["batchsim"]["worlds"]) == [3]
    assert sorted(attachments) == ["batchsim/view_geometry.yard.npz", "batchsim/yard/model.mjb"]  # group arms has no world in it
    done = _resim(str(path))  # the one topic recorded is compared: the rover's
    assert done.returncode == 0 and "world 3: 100 joint_states compared: bit-exact (every position, velocity and effort of 2 joints" in done.stdout, done.stdout


@pytest.mark.parametrize(
    "args, line",
    [
        (["--record-topics", "rover/joint_states,nothing"], "--record-topics names 'nothing', which no group of the recorded worlds publishes"),
        (["--record-topics", "rover/joint_states", "--record-worlds", "0,1"], "--record-topics names 'rover/joint_states', which no group of the recorded worlds publishes"),
        (["--record-worlds", "1,4"], "--record-worlds names world 4, which this fleet does not have (worlds 0..3)"),
    ],
)  # fmt: skip
def test_what_a_fleet_of_groups_cannot_record_is_one_line(depot, args, line, capsys, monkeypatch):
    domain = domain_id(61)
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    try:
        assert cli.main(["--fleet", str(depot), "--backend", "cpu", "--controllers", "none", "--bridge-workers", "1", *args]) == 2
    finally:
        release_domain(domain)
    assert capsys.readouterr().err.strip().splitlines()[-1] == f"batchsim: error: {line}"


def test_replay_publishes_every_groups_topics(recorded, tmp_path):
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile
    from sensor_msgs.msg import JointState

    picked = ["/world_0/arm/joint_states", "/world_3/rover/joint_states"]  # a world of each group
    with open(recorded, "rb") as f:
        expected = defaultdict(list)
        for _s, c, m in make_reader(f).iter_messages(topics=picked):
            expected[c.topic].append(m.data)
    domain = domain_id(61)
    os.environ.update(LOCALHOST)
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    node = Node("test_groups_replay_client", context=context)
    got: dict[str, list[bytes]] = {t: [] for t in picked}
    for topic in picked:
        node.create_subscription(JointState, topic, got[topic].append, QoSProfile(depth=1000), raw=True)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    proc = batchsim_process(["replay", str(recorded), "--worlds", "0,3", "--rate", "2", "--delay", "5"], domain, tmp_path / "log")
    try:
        spin_until_exit(executor, proc)
        log = (tmp_path / "log").read_text()
        assert proc.returncode == 0, log
        for topic in picked:
            assert len(expected[topic]) == PERIODS
            assert got[topic] == expected[topic], (topic, log)  # the recorded CDR bytes, every one, in order
        assert node.count_publishers("/world_2/arm/joint_states") == 0  # --worlds 0,3
    finally:
        if proc.poll() is None:
            proc.kill()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        release_domain(domain)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_recording_of_groups_in_the_view_draws_each_world_with_its_groups_robots(recorded, tmp_path):
    import numpy as np

    from ros_bridge.view_file import RecordingView

    lines: list[str] = []
    view = RecordingView(str(recorded), "127.0.0.1", _free_port(), lines.append)
    try:
        scene = view.scene
        assert [rows for _, rows in view.rec.parts] == [[0, 1], [2, 3]]
        arms, yard = (part.spec.geoms for part in scene.parts)
        assert not any(g.name.startswith("rover/") for g in arms) and any(g.name.startswith("rover/") for g in yard)
        view.slider.value = 0.5
        view.update()
        assert "**4 worlds**" in scene.fleet_text.content and "sim time 0.5" in scene.fleet_text.content
        for p, (part, handles) in enumerate(zip(scene.parts, scene.handles, strict=True)):
            assert len(handles) == len(part.spec.geoms)
            # each world's robots stand in its own cell of the fleet's grid: its poses from /tf, less
            # its cell's corner, are the recorded poses the group's first world has in its own cell
            moving = next(k for k, g in enumerate(part.spec.geoms) if g.anchor >= 0)
            at = handles[moving].batched_positions - scene.grid[list(part.worlds)]
            assert np.allclose(at[0], at[1], atol=1e-3), (p, at)
            assert np.linalg.norm(at[0]) < 5.0  # near the world's origin, not at another cell
        browser, pick = connect(scene)  # a browser's own pick (tests/view_clients.py)
        browser.type_world(3)
        wait(lambda: pick.world == 3, 10, "world 3 picked")
        view.update()
        assert pick.world_text.content == "**world_3** (world 3): running"
        browser.close()
    finally:
        view.scene.server.stop()
    log = tmp_path / "view.log"
    proc = subprocess.Popen([sys.executable, "-m", "batchsim.cli", "view", str(recorded), "--view-port", str(_free_port())],
                            stdout=open(log, "w"), stderr=subprocess.STDOUT)  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while "batchsim: view: http" not in log.read_text():
            assert proc.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.2)
        assert re.search(rf"\({re.escape(str(recorded))}: 4 worlds, sim time 0\.00 \.\. 0\.9\d s\)", log.read_text()), log.read_text()
    finally:
        proc.terminate()
        proc.wait(timeout=20)


def test_the_record_service_records_every_group(depot, tmp_path):
    from std_srvs.srv import SetBool

    path = tmp_path / "live.mcap"
    args = ["--fleet", str(depot), "--backend", "cpu", "--bridge-workers", "1", "--record", str(path)]
    with Fleet(domain_id(61), args, tmp_path / "batchsim.log") as fleet:
        fleet.wait_started()
        time.sleep(1.5)
        stopped = fleet.call(SetBool, "/batchsim/record", SetBool.Request(data=False))  # --record's, from the start
        assert stopped.success, stopped.message
        fleet.wait(lambda: f"messages in {path}" in fleet.log(), 30, "the first file finished")
        deadline = time.monotonic() + 10
        # the recorder said its last line; until its process is seen gone (a watch later), a start is refused
        while not (started := fleet.call(SetBool, "/batchsim/record", SetBool.Request(data=True))).success:
            assert started.message.startswith("still finishing") and time.monotonic() < deadline, started.message
            time.sleep(0.2)
        assert started.success and started.message == f"recording to {tmp_path / 'live_2.mcap'}", started.message
        time.sleep(1.5)
        stopped = fleet.call(SetBool, "/batchsim/record", SetBool.Request(data=False))
        assert stopped.success, stopped.message
        fleet.wait(lambda: f"messages in {tmp_path / 'live_2.mcap'}" in fleet.log(), 30, "the second file finished")
    for file in (path, tmp_path / "live_2.mcap"):
        _summary, metadata, _attachments, times, _ = _read(file)
        assert json.loads(metadata["batchsim"]["worlds"]) == [0, 1, 2, 3]
        for w, robot in ROBOTS:
            assert len(times[f"/world_{w}/{robot}/joint_states"]) > 10, (file, w, robot)
        assert len(times["/clock"]) > 10
    # the second began mid-run: each group's worlds re-run from the states its start took
    done = _resim(str(tmp_path / "live_2.mcap"))
    assert done.returncode == 0 and done.stdout.count("bit-exact") == 4, done.stdout + done.stderr
