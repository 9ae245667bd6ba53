"""`batchsim view FILE`: a recording (`batchsim --record`) in the web view, scrubbed through.

The page is the live view's (ros_bridge/worker/view_scene.py's FleetScene); the robots' geoms come
from the recording's `batchsim/view_geometry.npz` attachment, their poses from its `/tf` and
`/tf_static`: each world's anchor frames composed up to the fleet frame, at most FRAME_RATE
frames per sim second, and each browser's picked world's joint positions from its
`joint_states` (every browser keeps its own pick, view_scene.py's Pick). A slider picks the sim
time and `play` runs it at real time, the same for every browser. The worlds' status comes
from the recording's `/diagnostics` (worker/status_recording.py): each world is tinted and a
picked one's status said as the live view does; a recording without it says so. The file is read as
a stream: one cut short shows what was complete, after one line that says so.

A recording of a fleet of several groups of worlds (batchsim.fleet.groups) carries each group's
geometry as an attachment of its own (`batchsim/view_geometry.<group>.npz`), which its `batchsim`
metadata's `groups` names beside the group's worlds: each world is drawn with its group's robots,
and /tf's messages of one sim time (one per group) make one frame.
"""

from __future__ import annotations

import json
import os
import time as wallclock
from collections.abc import Callable
from typing import Any, BinaryIO

import numpy as np
from mcap.reader import NonSeekingReader
from mcap_ros2.decoder import DecoderFactory

from ros_bridge.mcap_index import IndexedFile, NoIndex
from ros_bridge.naming import frame
from ros_bridge.recording_file import ReplayError, check_file, cut_short_errors
from ros_bridge.view_plan import GEOMETRY, ViewSpec, geometry_from_bytes
from ros_bridge.worker.view_scene import CONTROLS_ORDER, FleetScene, ScenePart, qmul, rotate
from ros_bridge.world_status import from_values, status_text

FRAME_RATE = 30.0  # frames per sim second kept from the recording
FLEET_FRAME = "world"
IDENTITY = np.array([0, 0, 0, 1.0, 0, 0, 0])


def _transform(t) -> np.ndarray:
    """A geometry_msgs/Transform as (7,): translation, rotation w x y z."""
    r = t.rotation
    return np.array([t.translation.x, t.translation.y, t.translation.z, r.w, r.x, r.y, r.z])


def _every(times: np.ndarray) -> list[int]:
    """Indices of the log times (ns, ascending) kept at most FRAME_RATE a sim second, as the stream
    reader keeps them: each at least 1/FRAME_RATE s after the one kept before."""
    kept, last = [], -np.inf
    for k, t in enumerate(times.tolist()):
        if t >= last + 1e9 / FRAME_RATE:
            kept.append(k)
            last = t
    return kept


def _transforms(msg: Any) -> dict[str, tuple[str, np.ndarray]]:
    """A TFMessage's transforms: child frame -> (parent frame, pose (7,))."""
    return {t.child_frame_id: (t.header.frame_id, _transform(t.transform)) for t in msg.transforms}


def _compose(parent: np.ndarray, child: np.ndarray) -> np.ndarray:
    """(..., 7) poses parent ∘ child."""
    p = parent[..., :3] + rotate(parent[..., 3:], child[..., :3])
    return np.concatenate([p, qmul(parent[..., 3:], child[..., 3:])], -1)


class Recording:
    """What a recording holds for the view. ReplayError: one line naming the problem.

    A complete file is read through its indexes (ros_bridge/mcap_index.py): its /tf_static and
    /diagnostics whole, /tf's message times, and a frame's /tf and a world's joint_states when shown
    (`transforms`, `joint_series`), so a thousand worlds open in seconds. A file cut short is read
    as a stream, every kept frame decoded."""

    def __init__(self, path: str, say: Callable[[str], None]):
        complete = check_file(path)
        if not complete:
            say(f"warning: {path} was cut short (it has no summary: was the recorder killed?); showing its complete chunks")
        else:
            say(f"reading {path} ({os.path.getsize(path) / 1e6:.0f} MB) for the view ...")
        self.namespaces: list[str] = []
        # per group (one: every world): its geometry attachment's bytes and its worlds' rows in `namespaces`
        self.parts: list[tuple[bytes, list[int]]] = []
        self.joint_names: tuple[str, ...] = ()
        self.static: dict[str, tuple[str, np.ndarray]] = {}  # child frame -> (parent, pose)
        self._decoders: dict[int, Callable] = {}
        self._factory = DecoderFactory()
        self._file: IndexedFile | None = None
        self._moving: list[dict[str, tuple[str, np.ndarray]]] = []  # streamed: each kept frame's transforms
        self._joints: dict[str, list[tuple[int, np.ndarray]]] = {}  # streamed: per topic, (log time, positions)
        self._joint_indexes: dict[str, np.ndarray] = {}  # indexed: per topic, its messages' index entries
        self._read_head(path)
        statuses: list[tuple[int, list[tuple[str, int, int]]]] = []  # (log time, [(namespace, bits, flags)])
        times: list[int] = []
        self._stream: BinaryIO | None = None  # an indexed file's, kept open: frames are read when shown
        if complete:
            stream = open(path, "rb")  # noqa: SIM115
            try:
                self._file, self._stream = IndexedFile(stream), stream
            except NoIndex:
                stream.close()
            except cut_short_errors() as e:
                stream.close()
                raise ReplayError(f"{path}: unreadable ({type(e).__name__}: {e})") from None
        if self._file is not None:
            times = self._read_indexed(statuses)
        else:
            times = self._read_stream(path, complete, statuses)
        if not self.parts:
            raise ReplayError(f"{path} holds no robot geometry for the view (record it with batchsim --record)")
        if not times:
            raise ReplayError(f"{path} holds no /tf: the view draws the robots from it (record /tf)")
        self.times = np.array(times) * 1e-9
        self.has_status = bool(statuses)
        self.status, self.flags = self._status_at(statuses)

    def close(self) -> None:
        if self._stream is not None:
            self._stream.close()

    def _decode(self, channel: Any, schema: Any, data: bytes) -> Any:
        decode = self._decoders.get(channel.id)
        if decode is None:
            decode = self._decoders[channel.id] = self._factory.decoder_for(channel.message_encoding, schema)
        return decode(data)

    def _decode_entry(self, entry: Any) -> Any:
        f = self._file
        channel = f.channels[int(entry["channel"])]
        return self._decode(channel, f.schemas.get(channel.schema_id), f.data(entry))

    def _read_indexed(self, statuses: list) -> list[int]:
        """The index's /tf times (at most FRAME_RATE a sim second), /tf_static and /diagnostics."""
        f = self._file
        for entry in f.index(f.channel_ids(lambda t: t == "/tf_static")):
            self.static.update(_transforms(self._decode_entry(entry)))
        for entry in f.index(f.channel_ids(lambda t: t == "/diagnostics")):
            msg = self._decode_entry(entry)
            statuses.append((int(entry["time"]), [(s.hardware_id, *from_values({v.key: v.value for v in s.values})) for s in msg.status]))
        tf = f.index(f.channel_ids(lambda t: t == "/tf"))
        unique = np.unique(tf["time"])  # one sim time: each group's /tf of that frame
        kept = unique[_every(unique)].tolist()
        starts = np.searchsorted(tf["time"], kept)
        ends = np.searchsorted(tf["time"], kept, side="right")
        self._frames = [tf[a:b] for a, b in zip(starts, ends, strict=True)]
        self._groups = max((len(x) for x in self._frames), default=0)
        first = f.index(f.channel_ids(lambda t: t.endswith("/joint_states"))[:1])
        if len(first):
            self.joint_names = tuple(self._decode_entry(first[0]).name)
        return kept

    def _read_stream(self, path: str, complete: bool, statuses: list) -> list[int]:
        """A file without an index (cut short): every message, in the order written."""
        times: list[int] = []
        last: dict[str, int] = {}  # per topic, the log time of the last message kept
        with open(path, "rb") as f:
            try:
                for schema, channel, message in NonSeekingReader(f).iter_messages(log_time_order=False):
                    topic = channel.topic
                    if topic not in ("/tf", "/tf_static", "/diagnostics") and not topic.endswith("/joint_states"):
                        continue
                    if topic == "/diagnostics":  # every change is kept: a world froze at that period
                        msg = self._decode(channel, schema, message.data)
                        statuses.append((message.log_time, [(s.hardware_id, *from_values({v.key: v.value for v in s.values})) for s in msg.status]))
                        continue
                    same = topic in last and message.log_time == last[topic]  # another group's /tf of that frame
                    if topic != "/tf_static" and not same and topic in last and message.log_time < last[topic] + 1e9 / FRAME_RATE:
                        continue  # at most FRAME_RATE frames per sim second
                    last[topic] = message.log_time
                    msg = self._decode(channel, schema, message.data)
                    if topic == "/tf_static":
                        self.static.update(_transforms(msg))
                    elif topic == "/tf":
                        if same:
                            self._moving[-1].update(_transforms(msg))
                        else:  # a group whose /tf skipped this frame keeps its last poses
                            self._moving.append({**(self._moving[-1] if self._moving else {}), **_transforms(msg)})
                            times.append(message.log_time)
                    else:
                        self._joints.setdefault(topic, []).append((message.log_time, np.array(msg.position)))
                        self.joint_names = self.joint_names or tuple(msg.name)
            except cut_short_errors() as e:
                if complete:
                    raise ReplayError(f"{path}: unreadable ({type(e).__name__}: {e})") from None
        return times

    def transforms(self, k: int) -> dict[str, tuple[str, np.ndarray]]:
        """Frame `k`'s moving transforms: child frame -> (parent, pose). A group whose /tf skipped
        that frame keeps its poses of the frame before."""
        if self._file is None:
            return self._moving[k]
        out: dict[str, tuple[str, np.ndarray]] = {}
        frames = ([self._frames[k - 1]] if k and len(self._frames[k]) < self._groups else []) + [self._frames[k]]
        for entries in frames:
            for entry in entries:
                out.update(_transforms(self._decode_entry(entry)))
        return out

    def joint_series(self, world: int, t: float, span: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
        """World `world`'s joint positions over (t - span, t]: (times (n,), positions (n, njoint)),
        at most FRAME_RATE a sim second."""
        ns = self.namespaces[world]
        topic = f"/{ns}/joint_states" if ns else "/joint_states"
        if self._file is None:
            series = [(s[0] * 1e-9, s[1]) for s in self._joints.get(topic, []) if t - span <= s[0] * 1e-9 <= t]
        else:
            entries = self._joint_index(topic)
            lo, hi = np.searchsorted(entries["time"], [int((t - span) * 1e9), int(t * 1e9)], side="right")
            picked = entries[lo:hi]
            series = [(int(e["time"]) * 1e-9, np.array(self._decode_entry(e).position)) for e in picked[_every(picked["time"])]]
        if not series:
            return np.zeros(0), np.zeros((0, len(self.joint_names)))
        return np.array([s[0] for s in series]), np.array([s[1] for s in series])

    def _joint_index(self, topic: str) -> np.ndarray:
        if topic not in self._joint_indexes:
            self._joint_indexes[topic] = self._file.index(self._file.channel_ids(lambda t: t == topic))
        return self._joint_indexes[topic]

    def _status_at(self, statuses: list[tuple[int, list[tuple[str, int, int]]]]) -> tuple[np.ndarray, np.ndarray]:
        """(ntime, nworld) status bits and flags at each kept time: the newest /diagnostics word
        of each world at or before it."""
        row = {ns: w for w, ns in enumerate(self.namespaces)}
        bits = np.zeros((len(self.times), len(self.namespaces)), np.uint8)
        flags = np.zeros_like(bits)
        now_bits, now_flags = bits[0].copy(), flags[0].copy()
        statuses.sort(key=lambda s: s[0])
        j = 0
        for k, t in enumerate(self.times):
            while j < len(statuses) and statuses[j][0] * 1e-9 <= t + 1e-9:
                for ns, b, f in statuses[j][1]:
                    if ns in row:
                        now_bits[row[ns]], now_flags[row[ns]] = b, f
                j += 1
            bits[k], flags[k] = now_bits, now_flags
        return bits, flags

    def _read_head(self, path: str) -> None:
        """The metadata (the worlds, a fleet's groups) and the geometry attachments, at the file's
        start (before its first chunk): `parts`."""
        from mcap.records import Attachment, Chunk, Message, Metadata
        from mcap.stream_reader import StreamReader

        groups: list[dict] | None = None
        worlds: list[int] = []
        geometry: dict[str, bytes] = {}
        with open(path, "rb") as f:
            try:
                for record in StreamReader(f, emit_chunks=True).records:
                    if isinstance(record, Metadata) and record.name == "batchsim":
                        self.namespaces = json.loads(record.metadata.get("namespaces", "[]"))
                        worlds = json.loads(record.metadata.get("worlds", "[]"))
                        groups = json.loads(record.metadata["groups"]) if "groups" in record.metadata else None
                    elif isinstance(record, Attachment) and record.name.startswith(GEOMETRY.rsplit(".", 1)[0]):
                        geometry[record.name] = record.data
                    elif isinstance(record, Chunk | Message):
                        break
            except cut_short_errors():
                pass
        if groups is None:  # one group: every world draws the one geometry
            if GEOMETRY in geometry:
                self.parts = [(geometry[GEOMETRY], list(range(len(self.namespaces))))]
            return
        row = {w: k for k, w in enumerate(worlds)}
        for group in groups:
            rows = [row[w] for w in group["worlds"] if w in row]
            if rows and group.get("geometry") in geometry:
                self.parts.append((geometry[group["geometry"]], rows))

    def anchor_poses(self, k: int, frames: list[str], rows: list[int]) -> np.ndarray:
        """(len(rows), nanchor, 7): the worlds `rows`' anchor frames in the fleet frame at frame `k`,
        each world's transforms up the tree composed, a level of the tree at a time for every world."""
        transforms = self.transforms(k)
        names = [frame(self.namespaces[r], name) for r in rows for name in frames]
        pose = np.tile(IDENTITY, (len(names), 1))
        for _ in range(256):
            up = [n for n in names if n != FLEET_FRAME]
            if not up:
                break
            local = np.tile(IDENTITY, (len(names), 1))
            for i, n in enumerate(names):
                if n != FLEET_FRAME:
                    parent, local[i] = transforms.get(n) or self.static.get(n) or (FLEET_FRAME, IDENTITY)
                    names[i] = parent
            pose = _compose(local, pose)
        return pose.reshape(len(rows), len(frames), 7)


class RecordingView:
    """`path`'s page, served at host:port: the recording read (`rec`), each group's worlds drawn
    with its own geometry (`scene`, a FleetScene), a slider for the sim time and `play`."""

    def __init__(self, path: str, host: str, port: int, say: Callable[[str], None]):
        self.path = path
        self.rec = rec = Recording(path, say)
        parts, self.anchors = [], []  # per part: its anchor frames and its worlds' rows
        for data, rows in rec.parts:
            spec, frames = geometry_from_bytes(data, host, port)
            self.anchors.append((frames, rows))
            joints = (-1, (), rec.joint_names) if rec.joint_names else None
            parts.append(ScenePart(ViewSpec(spec.geoms, -1, spec.spacing, host, port, joints), tuple(rows)))
        drawn = {r for _, rows in rec.parts for r in rows}
        missing = [r for r in range(len(rec.namespaces)) if r not in drawn]
        if missing:  # a group whose geometry is not in the file: its worlds, without robots
            parts.append(ScenePart(ViewSpec((), -1, 1.0, host, port), tuple(missing)))
            self.anchors.append(([], missing))
        self.scene = scene = FleetScene(parts, rec.namespaces)
        gui = scene.server.gui
        self.t0, self.t1 = t0, t1 = float(rec.times[0]), float(rec.times[-1])
        self.step = step = float(np.median(np.diff(rec.times))) if len(rec.times) > 1 else 0.01
        self.slider = gui.add_slider("sim time (s)", min=t0, max=max(t1, t0 + step), step=step, initial_value=t0, order=CONTROLS_ORDER)
        self.play = gui.add_checkbox("play", False, order=CONTROLS_ORDER + 1)
        self.shown_frame = -1
        self._last = wallclock.monotonic()

    def update(self) -> None:
        """Play on (while `play`), and show the slider's time where it changed, and each browser's
        picked world where it or the time changed."""
        rec, scene = self.rec, self.scene
        now = wallclock.monotonic()
        if self.play.value:
            self.slider.value = self.t0 + (self.slider.value - self.t0 + now - self._last) % max(self.t1 - self.t0, self.step)
        self._last = now
        k = int(np.clip(np.searchsorted(rec.times, self.slider.value), 0, len(rec.times) - 1))
        if k != self.shown_frame:  # the frame's poses, computed for the frame shown
            self.shown_frame = k
            for p, (frames, rows) in enumerate(self.anchors):
                scene.draw(rec.anchor_poses(k, frames, rows), p)
            if rec.has_status:
                scene.tint(rec.status[k], rec.flags[k])
            scene.fleet_text.content = (
                f"**{len(rec.namespaces)} worlds** · {self.path} · sim time {rec.times[k]:.2f} s of {self.t0:.2f} .. {self.t1:.2f} s"
            )
        for pick in scene.picks():
            w = pick.world
            if pick.panel == (k, w):
                continue
            pick.panel = (k, w)
            with pick.client.atomic():
                pick.show_part()
                if rec.has_status:
                    name = rec.namespaces[w] or "/"
                    pick.world_text.content = f"**{name}** (world {w}): {status_text(int(rec.status[k, w]), int(rec.flags[k, w]))}"
                else:
                    pick.world_text.content = "the worlds' status is not in this recording (record /diagnostics)"
                t, q = rec.joint_series(w, float(rec.times[k]))
                if len(t):
                    pick.plot_joints(t, q)


def serve(path: str, host: str, port: int, say: Callable[[str], None], stop: Callable[[], bool] = lambda: False) -> None:
    """Serve `path`'s view until `stop()` (or Ctrl-C)."""
    view = RecordingView(path, host, port, say)
    rec = view.rec
    say(f"view: {view.scene.url} ({path}: {len(rec.namespaces)} worlds, sim time {view.t0:.2f} .. {view.t1:.2f} s)")
    try:
        while not stop():
            view.update()
            wallclock.sleep(0.05)
    finally:
        view.scene.server.stop()
        rec.close()
