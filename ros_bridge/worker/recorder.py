"""The recorder process: `python -m ros_bridge.worker.recorder STATUS_FD` (ros_bridge/recording.py
starts it and hands it the plan, the robots' geometry and the file's path on standard input; in
a fleet of several groups of worlds, every group's plan and geometry, for one file of them all).

It attaches the shared memory, lays out every recorded message with the bridge workers' own
CDR templates (messages.py's BulkMessages, tf.py's TfTemplate), and writes the periods the
loop queues in the recording ring (ros_bridge/protocol/recording.py) into one MCAP file as
rosbag2's MCAP storage writes a bag: profile `ros2`, one channel per topic, `cdr` messages
with `ros2msg` schemas (schemas.py), zstd-compressed chunks with message indexes, a summary
at the end. Every stamp and log time is sim time. A chunk is closed at least once a second,
so a recorder killed outright leaves a file readable up to its last complete chunk.
Recorded camera and lidar topics come from the sensor blocks, not the ring
(sensor_recording.py), looked at on every pass.

It reports `ready` on STATUS_FD once the file has its header, and lines for the log after
that; it finishes the file when standard input reaches EOF (the recording was stopped) or
on SIGTERM (the physics process went), after taking what the ring still holds. A write that
fails (a full disk) ends the recording with one line; the simulation goes on.
"""

from __future__ import annotations

import json
import os
import pickle
import select
import signal
import sys
import time as wallclock
from collections.abc import Callable, Sequence
from typing import Any, BinaryIO

import numpy as np
from mcap import __version__ as mcap_version
from rclpy.serialization import serialize_message
from std_msgs.msg import String

from batchsim.memory import Memory
from batchsim.resim.layout import METADATA as RESIM_METADATA
from batchsim.resim.layout import resim_names
from batchsim.stamps import stamp_of
from ros_bridge.naming import topic_name
from ros_bridge.plan import FLAG_FROZEN, FleetPlan
from ros_bridge.protocol.commands import RejectionWriter
from ros_bridge.protocol.recording import GroupsReader, RecordedPeriod, RecordReader, set_recording
from ros_bridge.view_plan import geometry_attachment
from ros_bridge.worker.input_topics import InputTopics
from ros_bridge.worker.mcap_file import BlockWriter
from ros_bridge.worker.messages import clock_payload
from ros_bridge.worker.process import die_with_parent
from ros_bridge.worker.schemas import qos_metadata, schema_text
from ros_bridge.worker.sensor_recording import SensorRecording, missed_line
from ros_bridge.worker.snapshot import Output
from ros_bridge.worker.status_recording import MSG_TYPE as STATUS_TYPE
from ros_bridge.worker.status_recording import TOPIC as STATUS_TOPIC
from ros_bridge.worker.status_recording import StatusRecording
from ros_bridge.worker.tf import TfTemplate, static_message

CHUNK_BYTES = 1 << 20  # a chunk closes at this size (uncompressed), or after CHUNK_SECONDS
CHUNK_SECONDS = 1.0
POLL = 0.01  # s between two looks at the ring
PROFILE = "ros2"
NICE = 10


class _Group:
    """One group's share of a recording (a fleet of one group: the whole of it): its recorded
    worlds' outputs (each world's channel), its tf template and its worlds' /diagnostics."""

    def __init__(self, plan: FleetPlan, channel: Callable[..., int], memory: Memory | None = None):
        spec = plan.recording
        self.spec, self.tf_spec = spec, plan.tf
        self.worlds = [plan.world_offset + w for w in spec.worlds]
        self.namespaces = [plan.namespaces[w] for w in spec.worlds]
        self.outputs = [Output(plan.outputs[i], self.namespaces) for i in spec.outputs]
        self.channels = [  # per output, each recorded world's channel id
            np.array([channel(topic_name(ns, out.spec.topic), out.spec.msg_type) for ns in self.namespaces])
            for out in self.outputs
        ]
        self.tf = TfTemplate(plan.tf, self.namespaces) if spec.tf and plan.tf.all_moving else None
        rejections = None
        if memory is not None:  # the live counts of rejected commands, from the bridge's memory
            rejections = (RejectionWriter(memory, "rej"), RejectionWriter(memory, "hrej"), np.asarray(spec.worlds, np.intp))
        self.status = StatusRecording(self.namespaces, rejections) if spec.diagnostics else None


class McapRecording:
    """One MCAP file of `plan.recording`'s topics and worlds; of a fleet of several groups
    (batchsim.fleet.groups), every group's: `plan` is then a list of (plan, geometry, name) per
    group, the first group's first (its periods give /clock), and each topic is one channel
    however many groups write it. A group's geometry (view_plan.py), where given, goes into the
    file as an attachment for `batchsim view FILE`.

    Raises OSError where the file cannot be written."""

    def __init__(
        self,
        plan: FleetPlan | Sequence[tuple[FleetPlan, bytes | None, str]],
        stream: BinaryIO,
        memories: Sequence[Memory] | None = None,
        resim: Sequence[dict | None] | None = None,
    ):
        groups = [(plan, None, "")] if isinstance(plan, FleetPlan) else list(plan)
        self.spec = groups[0][0].recording
        self.writer = BlockWriter(stream, chunk_bytes=CHUNK_BYTES, compression="zstd")
        self.writer.start(profile=PROFILE, library=f"batchsim (mcap {mcap_version})")
        self._schemas: dict[str, int] = {}
        self._topics: dict[str, int] = {}
        self.groups: list[_Group] = []
        metadata = {"namespaces": [], "worlds": []}
        for p, _, _ in groups:
            spec = p.recording
            metadata["namespaces"] += [p.namespaces[w] for w in spec.worlds]
            metadata["worlds"] += [p.world_offset + w for w in spec.worlds]
        head = {k: json.dumps(v) for k, v in metadata.items()} | {"control_rate": f"{groups[0][0].control_rate:g}"}
        if len(groups) > 1:  # which worlds are whose, and the name of each group's geometry
            head["groups"] = json.dumps([
                {"name": name, "worlds": [p.world_offset + w for w in p.recording.worlds],
                 "geometry": geometry_attachment(name) if geometry is not None else ""}
                for p, geometry, name in groups
            ])  # fmt: skip
        self.writer.add_metadata("batchsim", head)  # first: a replay picks worlds by it before their channels come
        memories = list(memories) if memories is not None else [None] * len(groups)
        self.groups = [_Group(p, self.channel, m) for (p, _, _), m in zip(groups, memories, strict=True)]
        self.namespaces = [ns for g in self.groups for ns in g.namespaces]
        self.tf_channel = (
            self.channel("/tf", "tf2_msgs/msg/TFMessage", depth=100) if any(g.tf is not None for g in self.groups) else -1
        )
        self.clock_channel = self.channel("/clock", "rosgraph_msgs/msg/Clock", depth=1) if self.spec.clock else -1
        diagnostics = any(g.status is not None for g in self.groups)
        self.status_channel = self.channel(STATUS_TOPIC, STATUS_TYPE) if diagnostics else -1
        self._latched = any(g.spec.tf_static or g.spec.description for g in self.groups)
        self._last_clock = -1
        self.writer.flush()
        for _, geometry, name in groups:  # the robots' geoms, for `batchsim view FILE` (ros_bridge/view_plan.py)
            if geometry is not None:
                self.writer.add_attachment(0, 0, geometry_attachment(name if len(groups) > 1 else None), "application/x-npz", geometry)
        # every period's inputs, for `batchsim resim` (batchsim.resim): per group that records them, its
        # model, its METADATA record (several groups: one each, naming its group) and its topics
        self.inputs: list[InputTopics] = []
        for g, (source, memory, (_, _, name)) in enumerate(zip(resim or (), memories, groups, strict=False)):
            if source is None or memory is None:
                continue
            names = resim_names(name)
            self.writer.add_metadata(RESIM_METADATA, source["meta"])
            self.writer.add_attachment(0, 0, names.model, "application/x-mujoco-mjb", source["model"])
            self.inputs.append(InputTopics(memory, len(self.groups[g].namespaces), self.channel, self._add, names))

    def channel(self, topic: str, msg_type: str, depth: int = 10, latched: bool = False) -> int:
        """The channel of `topic` (its `msg_type`'s schema registered once), with the QoS rosbag2
        records (`depth`; `latched`: transient local), registered at its first call; its id."""
        known = self._topics.get(topic)
        if known is not None:  # another group's worlds write it too (/tf, /diagnostics)
            return known
        schema = self._schemas.get(msg_type)
        if schema is None:
            schema = self._schemas[msg_type] = self.writer.register_schema(
                name=msg_type, encoding="ros2msg", data=schema_text(msg_type).encode()
            )
        self._topics[topic] = channel = self.writer.register_channel(
            topic=topic,
            message_encoding="cdr",
            schema_id=schema,
            metadata={"offered_qos_profiles": qos_metadata(transient_local=latched, depth=depth)},
        )
        return channel

    def _add(self, channel: int, t: int, data: bytes) -> None:
        self.writer.add_message(channel, t, data)

    @property
    def messages(self) -> int:
        """Messages written so far."""
        return self.writer.messages

    def write(self, period: RecordedPeriod, group: int = 0) -> None:
        """One period's messages of `group`'s worlds, as the workers would have published them
        (after every group's inputs stamped at or before it: the file stays in log-time order)."""
        g = self.groups[group]
        sec, nanosec = stamp_of(period.time)
        t = sec * 1_000_000_000 + nanosec
        for inputs in self.inputs:
            inputs.take(t)
        if self._latched:
            self._write_latched(t, sec, nanosec)
        if group == 0 and self.clock_channel >= 0 and (t != self._last_clock or period.forced):
            self._last_clock = t
            self._add(self.clock_channel, t, clock_payload(sec, nanosec))
        nrow = len(g.namespaces)
        flags, status = period.flags[:nrow], period.status[:nrow]
        if g.status is not None:
            data = g.status.message(period.time, sec, nanosec, status, flags)
            if data is not None:
                self._add(self.status_channel, t, data)
        channels = period.channels
        frozen = (flags & FLAG_FROZEN) != 0 if flags.any() else None
        for out, ids in zip(g.outputs, g.channels, strict=True):
            spec = out.spec
            if not (period.forced or period.period % spec.every == 0) or any(
                c not in channels for c in spec.channels
            ):
                continue
            out.bulk.fill(out.values(channels), sec, nanosec)
            for block in out.bulk.groups:  # the rows of one message layout, a block each
                rows, buf = block.rows, block.buf
                if frozen is not None and spec.state:  # a frozen world's state is not published
                    live = ~frozen[rows]
                    rows, buf = rows[live], buf[live]
                self.writer.add_block(ids[rows], t, buf)
        tf = g.tf
        if tf is not None and g.tf_spec.channel in channels and (period.forced or period.period % g.tf_spec.every == 0):
            self._add(self.tf_channel, t, tf.fill(g.tf_spec.moving_transforms(channels[g.tf_spec.channel]), sec, nanosec))

    def _write_latched(self, t: int, sec: int, nanosec: int) -> None:
        """/tf_static (one message: every group's fixed transforms) and each world's
        robot_description, once, at the first period."""
        self._latched = False
        statics = [g for g in self.groups if g.spec.tf_static]
        if statics:
            message = static_message(statics[0].tf_spec, statics[0].namespaces, statics[0].spec.worlds, sec, nanosec)
            for g in statics[1:]:
                message.transforms += static_message(g.tf_spec, g.namespaces, g.spec.worlds, sec, nanosec).transforms
            channel = self.channel("/tf_static", "tf2_msgs/msg/TFMessage", depth=1, latched=True)
            self._add(channel, t, bytes(serialize_message(message)))
        for g in self.groups:
            if not g.spec.description:
                continue
            data = bytes(serialize_message(String(data=g.tf_spec.description)))
            for ns in g.namespaces:
                self._add(self.channel(topic_name(ns, "robot_description"), "std_msgs/msg/String", 1, True), t, data)

    def flush(self) -> None:
        """Close the chunk in progress and hand it to the file."""
        self.writer.flush()

    def finish(self) -> None:
        """The summary (statistics, indexes) and the footer."""
        self.writer.finish()


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    status = os.fdopen(int(argv[0]), "w", buffering=1)
    die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the physics process, which stops us
    stopping = []
    signal.signal(signal.SIGTERM, lambda signum, frame: stopping.append(signum))
    try:  # per group (one, or a fleet's several, the first's first): (plan, geometry, name); the file; per
        # group, the model and facts for re-simulation where inputs are recorded (ros_bridge/input_recording.py)
        groups, path, resim = pickle.load(sys.stdin.buffer)
    except (EOFError, pickle.UnpicklingError):
        return 0
    plans = [plan for plan, _, _ in groups]
    if not any(any(p.recording.sensors) for p in plans):  # a sensor block holds one sample: no slack for a camera's recorder
        os.nice(NICE)  # the ring gives it seconds of slack: the loop and the workers come first for the cores
    memories = [Memory.attach(p.layout, p.memory_name) for p in plans]
    reader = GroupsReader([RecordReader(m, p.recording.channels) for p, m in zip(plans, memories, strict=True)])
    recording: McapRecording | None = None
    stream: Any = None
    try:
        # a file made meanwhile is not written over (recording.path_problem); a device is written to
        stream = open(path, "wb" if os.path.exists(path) and not os.path.isfile(path) else "xb")
        recording = McapRecording(groups, stream, memories, resim)
        # cameras and lidars, each group's from its own blocks
        sensors = [SensorRecording(p, m, recording.channel, recording.writer) for p, m in zip(plans, memories, strict=True)]
        status.write("ready\n")
        flushed = wallclock.monotonic()
        while not stopping:
            ready, _, _ = select.select([sys.stdin.buffer], [], [], POLL)
            if ready and not os.read(sys.stdin.fileno(), 4096):
                break  # EOF: stopped
            for group, period in reader.take():
                recording.write(period, group)
            for s in sensors:
                s.take()
            if wallclock.monotonic() - flushed >= CHUNK_SECONDS:
                recording.flush()
                flushed = wallclock.monotonic()
        while reader.pending():  # the loop stopped writing before it told us: take what is left
            for group, period in reader.take():
                recording.write(period, group)
        for group, period in reader.take(final=True):
            recording.write(period, group)
        for s in sensors:
            s.take()
        for inputs in recording.inputs:
            inputs.take()  # every one left
        recording.finish()
        stream.close()
        dropped = reader.dropped()
        lost = f"; {dropped} periods dropped (the recorder fell behind the loop)" if dropped else ""
        lost += missed_line(sum(s.missed for s in sensors))
        lost += "".join(inputs.lost_line() for inputs in recording.inputs)
        status.write(f"recording: {recording.messages} messages in {path}{lost}\n")
        return 0
    except OSError as e:  # a full disk, a path that went away: the recording stops, the loop goes on
        for m in memories:
            set_recording(m, None)
        reason = e.strerror or str(e)
        status.write(f"warning: recording stopped: {path}: {reason}; the simulation goes on\n")
        return 1
    finally:
        for m in memories:
            m.close()


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)  # skip the interpreter's teardown of rclpy's message modules
