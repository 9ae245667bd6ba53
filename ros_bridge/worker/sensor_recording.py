"""The recorder's cameras and lidars (ros_bridge/worker/recorder.py hooks this in): the
recorded worlds' images, camera infos, scans and clouds, read from the sensor blocks the
workers read (ros_bridge/protocol/sensor_blocks.py) and written into the MCAP file as the
workers would publish them: the same bulk CDR framing (sensor_messages.py), one channel per
topic and world, stamped and logged at the sim time of the sample.

The physics side renders and scans the recorded topics for the recorded worlds while the
recording runs (ros_bridge/recording.py's `want_sensors`), at each sensor's own rate. A
block holds one sample per world, so the recorder takes new samples at every look (every
POLL, 10 ms) and keeps the seq it took in `rec.sensors.seen`: with `--rtf 0` the physics
side waits on it before overwriting a sample; otherwise a sample overwritten before the
recorder looked is counted (`missed`) and reported in the recorder's closing line.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from batchsim.sensors import Lidar
from batchsim.stamps import stamp_of
from ros_bridge.plan import FleetPlan
from ros_bridge.protocol.sensor_blocks import PART_BITS, SensorBlock, missed
from ros_bridge.worker.mcap_file import BlockWriter
from ros_bridge.worker.sensor_messages import Framing, topic_framing
from ros_bridge.worker.sensors import under


@dataclasses.dataclass
class _Topic:
    """One recorded topic of a sensor: `part` its payload (None: CameraInfo), `bit` the part's
    PART_BITS a sample must hold (0: any sample), `framing` and `channels` (per recorded world)."""

    part: str | None
    bit: int
    framing: Framing
    channels: np.ndarray


@dataclasses.dataclass
class _Sensor:
    block: SensorBlock
    seen: np.ndarray  # (recorded worlds,) a view of rec.sensors.seen's column
    topics: list[_Topic]
    points: Callable[[np.ndarray], np.ndarray] | None = None  # a 3D lidar: ranges -> xyz


class SensorRecording:
    """The recorded camera and lidar topics of `plan.recording`'s worlds.

    Args:
      plan: the fleet's plan (`recording.sensors` says which topics).
      memory: the shared arrays.
      channel: registers a channel, `channel(topic, msg_type) -> id` (McapRecording's).
      writer: the file.

    Attributes:
      messages: messages written; missed: samples overwritten before the recorder took them.
    """

    def __init__(self, plan: FleetPlan, memory, channel: Callable[[str, str], int], writer: BlockWriter):
        spec, sensors = plan.recording, plan.sensors
        self.writer = writer
        self.worlds = np.array(spec.worlds, np.intp)
        self.messages = 0
        self.missed = 0
        self.sensors: list[_Sensor] = []
        if sensors is None or not any(spec.sensors):  # no camera or lidar topic recorded
            return
        namespaces = [plan.namespaces[w] for w in spec.worlds]
        seen = memory["rec.sensors.seen"]
        by_sensor: dict[int, list[_Topic]] = {}
        for t in sensors.topics():  # the recorded ones, framed as the workers frame them
            if not spec.sensors[t.sensor] & t.want:
                continue
            source, rate = sensors.source(t.sensor)
            names = ["/" + n for n in under(namespaces, t.name)]
            framing = topic_framing(t.kind, source, rate, under(namespaces, source.frame_id), names[0])
            ids = np.array([channel(n, t.kind.msg_type) for n in names], np.int64)
            by_sensor.setdefault(t.sensor, []).append(_Topic(t.part, PART_BITS[t.part] if t.part else 0, framing, ids))
        for s, topics in by_sensor.items():
            source, _ = sensors.source(s)
            points = source.points if isinstance(source, Lidar) and source.is_3d else None
            self.sensors.append(_Sensor(sensors.block(memory, s), seen[:, s], topics, points))
        for sensor in self.sensors:  # from now on: a sample written before the recording is not taken
            seq = sensor.block.seq[self.worlds]
            sensor.seen[:] = seq - seq % 2

    def take(self) -> None:
        """Write every sample of the recorded worlds written since the last call."""
        for sensor in self.sensors:
            before = sensor.seen.copy()
            rows, parts, time, data = sensor.block.read_worlds(self.worlds, sensor.seen)
            if not rows.size:
                continue
            self.missed += missed(before, sensor.seen.copy())
            if sensor.points is not None:
                data = {"ranges": sensor.points(data["ranges"])}
            for stamp in np.unique(time).tolist():  # spread over the sensor's period: a stamp or two
                sec, nanosec = stamp_of(stamp)
                t = sec * 1_000_000_000 + nanosec
                at = time == stamp
                for topic in sensor.topics:
                    keep = at & ((parts & topic.bit) != 0) if topic.bit else at
                    mine = rows[keep]
                    if not mine.size:
                        continue
                    payload = data[topic.part][keep] if topic.part is not None else None
                    for where, messages in topic.framing.block(mine, sec, nanosec, payload):
                        self.writer.add_block(topic.channels[mine[where]], t, messages)
                        self.messages += len(where)

    def closing(self) -> str:
        """For the recorder's closing line: the samples missed, if any."""
        return missed_line(self.missed)


def missed_line(missed: int) -> str:
    """For the recorder's closing line: `missed` samples (every group's), if any."""
    if not missed:
        return ""
    return f"; {missed} camera or lidar samples missed (overwritten before the recorder took them)"
