"""`batchsim view FILE`: a recording (`batchsim --record`) in the web view, scrubbed through.

The page is the live view's (ros_bridge/worker/view.py's FleetScene); the robots' geoms come
from the recording's `batchsim/view_geometry.npz` attachment, their poses from its `/tf` and
`/tf_static`: each world's anchor frames composed up to the fleet frame, at most FRAME_RATE
frames per sim second, and the picked world's joint positions from its `joint_states`. A
slider picks the sim time and `play` runs it at real time. The worlds' status comes from the
recording's `/diagnostics` (worker/status_recording.py): each world is tinted and the picked
one's status said as the live view does; a recording without it says so. The file is read as
a stream: one cut short shows what was complete, after one line that says so.

A recording of a fleet of several groups of worlds (batchsim.fleet.groups) carries each group's
geometry as an attachment of its own (`batchsim/view_geometry.<group>.npz`), which its `batchsim`
metadata's `groups` names beside the group's worlds: each world is drawn with its group's robots,
and /tf's messages of one sim time (one per group) make one frame.
"""

from __future__ import annotations

import json
import time as wallclock
from collections.abc import Callable

import numpy as np
from mcap.reader import NonSeekingReader
from mcap_ros2.decoder import DecoderFactory

from ros_bridge.naming import frame
from ros_bridge.recording_file import ReplayError, check_file, cut_short_errors
from ros_bridge.view_plan import GEOMETRY, ViewSpec, geometry_from_bytes
from ros_bridge.worker.view_scene import FleetScene, ScenePart, qmul, rotate
from ros_bridge.world_status import from_values, status_text

FRAME_RATE = 30.0  # frames per sim second kept from the recording
FLEET_FRAME = "world"
IDENTITY = np.array([0, 0, 0, 1.0, 0, 0, 0])


def _transform(t) -> np.ndarray:
    """A geometry_msgs/Transform as (7,): translation, rotation w x y z."""
    r = t.rotation
    return np.array([t.translation.x, t.translation.y, t.translation.z, r.w, r.x, r.y, r.z])


def _compose(parent: np.ndarray, child: np.ndarray) -> np.ndarray:
    """(..., 7) poses parent ∘ child."""
    p = parent[..., :3] + rotate(parent[..., 3:], child[..., :3])
    return np.concatenate([p, qmul(parent[..., 3:], child[..., 3:])], -1)


class Recording:
    """What a recording holds for the view. ReplayError: one line naming the problem."""

    def __init__(self, path: str, say: Callable[[str], None]):
        complete = check_file(path)
        if not complete:
            say(f"warning: {path} was cut short (it has no summary: was the recorder killed?); showing its complete chunks")
        self.namespaces: list[str] = []
        # per group (one: every world): its geometry attachment's bytes and its worlds' rows in `namespaces`
        self.parts: list[tuple[bytes, list[int]]] = []
        self.joint_names: tuple[str, ...] = ()
        static: dict[str, tuple[str, np.ndarray]] = {}  # child frame -> (parent, pose)
        moving: list[tuple[int, dict[str, tuple[str, np.ndarray]]]] = []  # (log time, child -> (parent, pose))
        joints: dict[str, list[tuple[int, np.ndarray]]] = {}
        statuses: list[tuple[int, list[tuple[str, int, int]]]] = []  # (log time, [(namespace, bits, flags)])
        decoders: dict[int, Callable] = {}
        factory = DecoderFactory()
        last: dict[str, int] = {}  # per topic, the log time of the last message kept
        with open(path, "rb") as f:
            try:
                for schema, channel, message in NonSeekingReader(f).iter_messages(log_time_order=False):
                    topic = channel.topic
                    if topic not in ("/tf", "/tf_static", "/diagnostics") and not topic.endswith("/joint_states"):
                        continue
                    if topic == "/diagnostics":  # every change is kept: a world froze at that period
                        msg = self._decoder(decoders, factory, schema, channel)(message.data)
                        statuses.append((message.log_time, [(s.hardware_id, *from_values({v.key: v.value for v in s.values})) for s in msg.status]))
                        continue
                    same = topic in last and message.log_time == last[topic]  # another group's /tf of that frame
                    if topic != "/tf_static" and not same and topic in last and message.log_time < last[topic] + 1e9 / FRAME_RATE:
                        continue  # at most FRAME_RATE frames per sim second
                    last[topic] = message.log_time
                    msg = self._decoder(decoders, factory, schema, channel)(message.data)
                    if topic == "/tf_static":
                        static.update({t.child_frame_id: (t.header.frame_id, _transform(t.transform)) for t in msg.transforms})
                    elif topic == "/tf":
                        transforms = {t.child_frame_id: (t.header.frame_id, _transform(t.transform)) for t in msg.transforms}
                        if same:
                            moving[-1][1].update(transforms)
                        else:  # a group whose /tf skipped this frame keeps its last poses
                            moving.append((message.log_time, {**(moving[-1][1] if moving else {}), **transforms}))
                    else:
                        joints.setdefault(topic, []).append((message.log_time, np.array(msg.position)))
                        self.joint_names = self.joint_names or tuple(msg.name)
            except cut_short_errors() as e:
                if complete:
                    raise ReplayError(f"{path}: unreadable ({type(e).__name__}: {e})") from None
        self._read_head(path)
        if not self.parts:
            raise ReplayError(f"{path} holds no robot geometry for the view (record it with batchsim --record)")
        if not moving:
            raise ReplayError(f"{path} holds no /tf: the view draws the robots from it (record /tf)")
        self.times = np.array([t for t, _ in moving]) * 1e-9
        self.static, self.moving, self.joints = static, moving, joints
        self.has_status = bool(statuses)
        self.status, self.flags = self._status_at(statuses)

    @staticmethod
    def _decoder(decoders: dict[int, Callable], factory: DecoderFactory, schema, channel) -> Callable:
        decode = decoders.get(channel.id)
        if decode is None:
            decode = decoders[channel.id] = factory.decoder_for(channel.message_encoding, schema)
        return decode

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

    def anchor_poses(self, frames: list[str], rows: list[int] | None = None) -> np.ndarray:
        """(ntime, nworld, nanchor, 7): each world's (the worlds `rows`', default all) anchor frames
        in the fleet frame, at each kept time."""
        namespaces = self.namespaces if rows is None else [self.namespaces[r] for r in rows]
        out = np.zeros((len(self.moving), len(namespaces), len(frames), 7))
        for k, (_t, transforms) in enumerate(self.moving):
            memo: dict[str, np.ndarray] = {}
            for w, ns in enumerate(namespaces):
                for a, name in enumerate(frames):
                    out[k, w, a] = self._pose(frame(ns, name), transforms, memo)
        return out

    def _pose(self, name: str, transforms: dict, memo: dict[str, np.ndarray]) -> np.ndarray:
        """Frame `name` in the fleet frame: its transforms up the tree, composed."""
        chain = []
        while name != FLEET_FRAME and name not in memo and len(chain) < 256:
            parent, local = transforms.get(name) or self.static.get(name) or (FLEET_FRAME, IDENTITY)
            chain.append((name, local))
            name = parent
        pose = memo.get(name, IDENTITY)
        for child, local in reversed(chain):
            pose = memo[child] = _compose(pose, local)
        return pose


class RecordingView:
    """`path`'s page, served at host:port: the recording read (`rec`), each group's worlds drawn
    with its own geometry (`scene`, a FleetScene), a slider for the sim time and `play`."""

    def __init__(self, path: str, host: str, port: int, say: Callable[[str], None]):
        self.path = path
        self.rec = rec = Recording(path, say)
        parts, self.poses = [], []
        for data, rows in rec.parts:
            spec, frames = geometry_from_bytes(data, host, port)
            self.poses.append(rec.anchor_poses(frames, rows))
            joints = (-1, (), rec.joint_names) if rec.joint_names else None
            parts.append(ScenePart(ViewSpec(spec.geoms, -1, spec.spacing, host, port, joints), tuple(rows)))
        drawn = {r for _, rows in rec.parts for r in rows}
        missing = [r for r in range(len(rec.namespaces)) if r not in drawn]
        if missing:  # a group whose geometry is not in the file: its worlds, without robots
            parts.append(ScenePart(ViewSpec((), -1, 1.0, host, port), tuple(missing)))
            self.poses.append(np.zeros((len(rec.times), len(missing), 0, 7)))
        self.scene = scene = FleetScene(parts, rec.namespaces)
        gui = scene.server.gui
        self.t0, self.t1 = t0, t1 = float(rec.times[0]), float(rec.times[-1])
        self.step = step = float(np.median(np.diff(rec.times))) if len(rec.times) > 1 else 0.01
        self.slider = gui.add_slider("sim time (s)", min=t0, max=max(t1, t0 + step), step=step, initial_value=t0)
        self.play = gui.add_checkbox("play", False)
        if not rec.has_status:
            scene.world_text.content = "the worlds' status is not in this recording (record /diagnostics)"
        self.shown = (-1, -1)
        self._last = wallclock.monotonic()

    def update(self) -> None:
        """Play on (while `play`), and show the slider's time and the picked world where either changed."""
        rec, scene = self.rec, self.scene
        now = wallclock.monotonic()
        if self.play.value:
            self.slider.value = self.t0 + (self.slider.value - self.t0 + now - self._last) % max(self.t1 - self.t0, self.step)
        self._last = now
        k = int(np.clip(np.searchsorted(rec.times, self.slider.value), 0, len(rec.times) - 1))
        w = scene.picked
        if (k, w) == self.shown:
            return
        self.shown = (k, w)
        scene.show_part()
        for p, poses in enumerate(self.poses):
            scene.draw(poses[k], p)
        if rec.has_status:
            scene.tint(rec.status[k], rec.flags[k])
            name = rec.namespaces[w] or "/"
            scene.world_text.content = f"**{name}** (world {w}): {status_text(int(rec.status[k, w]), int(rec.flags[k, w]))}"
        scene.fleet_text.content = (
            f"**{len(rec.namespaces)} worlds** · {self.path} · sim time {rec.times[k]:.2f} s of {self.t0:.2f} .. {self.t1:.2f} s"
        )
        series = rec.joints.get(f"/{rec.namespaces[w]}/joint_states" if rec.namespaces[w] else "/joint_states", [])
        if series:
            t = np.array([s[0] for s in series]) * 1e-9
            keep = (t <= rec.times[k]) & (t >= rec.times[k] - 10.0)
            if keep.any():
                scene.plot_joints(t[keep], np.array([s[1] for s, ok in zip(series, keep, strict=True) if ok]))


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
