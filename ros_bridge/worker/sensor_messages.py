"""Image, CameraInfo, LaserScan and PointCloud2 as CDR bytes, built in bulk (worker side).

A sensor message's serialized layout is fixed per world once its frame and sizes are set:
only the stamp (bytes 4..12, right after the encapsulation header: every message here
starts with a std_msgs/Header) and the payload (Image.data, LaserScan.ranges,
PointCloud2.data) change. So each world's message is serialized once, with a marker
payload, and split into a prefix and a suffix around it; a publish is then

    framing.payload(row, sec, nanosec, memoryview(rgb[row]))   # prefix + payload + suffix: one copy

handed to `Publisher.publish(bytes)` (no message object, no per-field conversion).
benchmarks/sensor_messages.py measures this against filling message objects. A recording
(sensor_recording.py) takes many rows at once: `framing.block(rows, sec, nanosec, rgb)` lays
them out as a (rows, bytes) array per prefix and suffix length, for mcap_file.py's blocks.
"""

from __future__ import annotations

import array
import struct
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CameraInfo, Image, LaserScan, PointCloud2, PointField

from batchsim.sensors import Camera, Lidar
from ros_bridge.sensor_topics import TopicKind
from ros_bridge.worker.messages import find_once, locate_stamps, set_stamp_marker

_STAMP = struct.Struct("<iI")
STAMP_AT = 4  # bytes: the header's stamp, after the 4-byte CDR encapsulation header


class Framing:
    """Per row (world), the serialized bytes before and after a message's payload.

    Args:
      messages: one message per row, its header's frame set, its payload field set by
        `fill(msg, marker)` to `nbytes` marker bytes (nothing when nbytes is 0).
      fill: sets the payload field of a message from bytes.
      nbytes: the payload's size in bytes.
      topic: for errors.
    """

    def __init__(self, messages: Sequence[Any], fill: Callable[[Any, bytes], None] | None, nbytes: int, topic: str):
        marker = ((np.arange(nbytes, dtype=np.uint32) * 7 + 13) % 251 + 3).astype(np.uint8).tobytes()
        self.nbytes = nbytes
        self.prefixes: list[bytearray] = []
        self.suffixes: list[bytes] = []
        for msg in messages:
            set_stamp_marker(msg.header.stamp)  # messages.py's markers: one way to find a stamp
            if fill is not None:
                fill(msg, marker)
            data = bytes(serialize_message(msg))
            if locate_stamps(data).tolist() != [STAMP_AT]:
                raise RuntimeError(f"{topic}: the header's stamp is not where CDR puts it")
            at = find_once(data, marker, topic) if nbytes else len(data)
            self.prefixes.append(bytearray(data[:at]))
            self.suffixes.append(data[at + nbytes :])
        self._layouts: list[tuple[np.ndarray, np.ndarray]] | None = None  # block()'s, made when first asked
        self._layout = np.zeros(0, np.intp)  # per row, its layout
        self._place = np.zeros(0, np.intp)  # per row, its place in its layout's arrays

    def payload(self, row: int, sec: int, nanosec: int, data: Any = b"") -> bytes:
        """Row `row`'s message stamped (sec, nanosec), its payload `data` (any buffer of nbytes)."""
        prefix = self.prefixes[row]
        _STAMP.pack_into(prefix, STAMP_AT, sec, nanosec)
        return b"".join((prefix, data, self.suffixes[row])) if self.nbytes else bytes(prefix)

    def block(
        self, rows: np.ndarray, sec: int, nanosec: int, data: np.ndarray | None = None
    ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """The messages of `rows` ((n,) row indices) stamped (sec, nanosec), row i's payload
        `data[i]` (data: (n, ...) of nbytes each, any dtype): per layout (rows whose prefix and
        suffix lengths agree; frame ids of other lengths pad differently), (positions in `rows`
        (m,), messages (m, L) uint8), each row what `payload` gives."""
        if self._layouts is None:
            self._lay_out()
        payload = np.ascontiguousarray(data).reshape(len(rows), -1).view(np.uint8) if self.nbytes else None
        stamp = np.frombuffer(_STAMP.pack(sec, nanosec), np.uint8)
        layout = self._layout[rows]
        for k in np.unique(layout).tolist():
            where = np.flatnonzero(layout == k)
            prefixes, suffixes = self._layouts[k]
            place = self._place[rows[where]]
            p = prefixes.shape[1]
            out = np.empty((len(where), p + self.nbytes + suffixes.shape[1]), np.uint8)
            out[:, :p] = prefixes[place]
            out[:, STAMP_AT : STAMP_AT + _STAMP.size] = stamp
            if payload is not None:
                out[:, p : p + self.nbytes] = payload[where]
            out[:, p + self.nbytes :] = suffixes[place]
            yield where, out

    def _lay_out(self) -> None:
        keys: dict[tuple[int, int], int] = {}
        members: list[list[int]] = []
        self._layout = np.empty(len(self.prefixes), np.intp)
        self._place = np.empty(len(self.prefixes), np.intp)
        for row, (prefix, suffix) in enumerate(zip(self.prefixes, self.suffixes, strict=True)):
            k = keys.setdefault((len(prefix), len(suffix)), len(keys))
            if k == len(members):
                members.append([])
            self._layout[row], self._place[row] = k, len(members[k])
            members[k].append(row)

        def stack(parts: list, rows: list[int]) -> np.ndarray:
            return np.array([np.frombuffer(bytes(parts[r]), np.uint8) for r in rows]).reshape(len(rows), -1)

        self._layouts = [(stack(self.prefixes, rows), stack(self.suffixes, rows)) for rows in members]


def _set_data(msg: Any, marker: bytes) -> None:
    msg.data = marker


def _set_ranges(msg: Any, marker: bytes) -> None:
    msg.ranges = array.array("f", marker)


def image_framing(camera: Camera, frames: Sequence[str], depth: bool, topic: str) -> Framing:
    """Image rgb8 (or 32FC1 depth in metres) of `camera`, one row per frame id."""
    h, w = camera.height, camera.width
    step = w * (4 if depth else 3)
    messages = []
    for frame in frames:
        msg = Image(height=h, width=w, encoding="32FC1" if depth else "rgb8", is_bigendian=0, step=step)
        msg.header.frame_id = frame
        messages.append(msg)
    return Framing(messages, _set_data, h * step, topic)


def camera_info_framing(camera: Camera, frames: Sequence[str], topic: str) -> Framing:
    """CameraInfo of `camera` (constant but for the stamp), one row per frame id."""
    info = camera.info
    messages = []
    for frame in frames:
        msg = CameraInfo(height=info.height, width=info.width, distortion_model=info.distortion_model)
        msg.d = [float(v) for v in info.d]
        msg.k = [float(v) for v in info.k]
        msg.r = [float(v) for v in info.r]
        msg.p = [float(v) for v in info.p]
        msg.header.frame_id = frame
        messages.append(msg)
    return Framing(messages, None, 0, topic)


def laser_scan_framing(lidar: Lidar, rate: float, frames: Sequence[str], topic: str) -> Framing:
    """LaserScan of a 2D lidar; its payload is the (nray,) float32 ranges, REP 117."""
    messages = []
    for frame in frames:
        msg = LaserScan(
            angle_min=float(lidar.angle_min),
            angle_max=float(lidar.angle_max),
            angle_increment=float(lidar.angle_increment),
            time_increment=0.0,  # every ray of a scan is cast at once
            scan_time=1.0 / rate,
            range_min=float(lidar.range_min),
            range_max=float(lidar.range_max),
        )
        msg.header.frame_id = frame
        messages.append(msg)
    return Framing(messages, _set_ranges, 4 * lidar.nray, topic)


def point_cloud_framing(lidar: Lidar, frames: Sequence[str], topic: str) -> Framing:
    """PointCloud2 of a 3D lidar: x, y, z float32, organized (height rows, width columns),
    not dense (NaN where a ray had no return)."""
    fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, n in enumerate("xyz")]
    messages = []
    for frame in frames:
        msg = PointCloud2(
            height=lidar.nrow, width=lidar.ncol, fields=fields, is_bigendian=False, point_step=12,
            row_step=12 * lidar.ncol, is_dense=False,
        )  # fmt: skip
        msg.header.frame_id = frame
        messages.append(msg)
    return Framing(messages, _set_data, 12 * lidar.nray, topic)


def topic_framing(kind: TopicKind, source: Camera | Lidar, rate: float | None, frames: Sequence[str], topic: str) -> Framing:
    """The framing of a `kind` topic (SensorPlan.topics()) of `source`, a Camera or a Lidar at
    `rate` Hz, over the worlds whose frame ids are `frames`; `topic` the first world's topic.
    The workers publish with it and the recorder records with it."""
    if kind is TopicKind.IMAGE or kind is TopicKind.DEPTH:
        return image_framing(source, frames, kind is TopicKind.DEPTH, topic)
    if kind is TopicKind.INFO:
        return camera_info_framing(source, frames, topic)
    if kind is TopicKind.CLOUD:
        return point_cloud_framing(source, frames, topic)
    return laser_scan_framing(source, rate, frames, topic)
