"""A recording, read for re-simulation: its inputs' layout and model, each world's starts and
inputs, and its recorded joint states. ResimError, one line, for a file that cannot be re-run."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence

import numpy as np

from batchsim.resim.layout import (
    METADATA,
    InputsLayout,
    ResimNames,
    model_hash,
    resim_names,
    unpack,
    unpack_string,
)
from batchsim.stamps import message_ns


class ResimError(Exception):
    """A recording that cannot be re-run as asked; its message is one line."""


@dataclasses.dataclass
class Start:
    """A world's (re)start: the period it starts in, its state (mjSTATE_INTEGRATION), its draw
    number and its drawn model values; `fresh`: at the run's first period or a reset (its
    controllers start afresh too), not a recording begun mid-run."""

    period: int
    state: np.ndarray
    draw: int
    params: dict[str, np.ndarray]
    fresh: bool = True


@dataclasses.dataclass
class JointStates:
    """One recorded sensor_msgs/JointState topic of a world: `stamps` (n,) int ns, `names` (the
    model's joint names: a robot's own prefixed `<robot>/` in a world of several robots),
    `position`, `velocity` and `effort` (n, njoint; NaN where a message has none)."""

    stamps: np.ndarray
    names: list[str]
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray | None = None


@dataclasses.dataclass
class TfStates:
    """A world's recorded moving transforms (/tf): `stamps` (n,) int ns, `pairs` its (parent,
    child) frames without the namespace, `values` (n, npair, 7): translation xyz, rotation xyzw."""

    stamps: np.ndarray
    pairs: list[tuple[str, str]]
    values: np.ndarray


@dataclasses.dataclass
class WorldRecord:
    """What the file holds of one world: its number, namespace, starts, every period's inputs
    (rows of the layout's input width), its joint states (one per recorded joint_states topic:
    the world's, or each robot's of a world of several; empty where none was recorded) and,
    where asked for, its /tf."""

    world: int
    namespace: str
    starts: list[Start]
    inputs: np.ndarray
    joint_states: list[JointStates]
    tf: TfStates | None = None
    # nav_msgs/Odometry topics asked for (relative to the namespace) -> (stamps (n,) ns, (n, 13)
    # position xyz, orientation xyzw, linear xyz, angular xyz)
    odometry: dict[str, tuple[np.ndarray, np.ndarray]] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass
class Recorded:
    """A recording's re-simulation facts, of one group of its fleet (its only one, or one of
    several models'): `meta` (the group's batchsim_resim record), `layout`, the MJB `model`
    bytes, the periods' `headers` (n, 3: number, sim time, steps), per world asked its
    WorldRecord, and the controllers' inputs (`events`: each a JSON document of
    ros_bridge/input_recording.py's, in period order). `group`: its name ("": a fleet of one)."""

    meta: dict[str, str]
    layout: InputsLayout
    model: bytes
    headers: np.ndarray
    worlds: dict[int, WorldRecord]
    events: list[dict] = dataclasses.field(default_factory=list)
    group: str = ""


def read(path: str, worlds: Sequence[int] | None = None, tf: bool = False, odometry: Sequence[str] = ()) -> list[Recorded]:
    """The re-simulation facts of `path` for `worlds` (fleet numbers; None: every recorded one),
    one Recorded per group of the fleet that holds any of them (a fleet of one model: one); with
    `tf`, their /tf too (every /tf message decoded: slow on large fleets); and the
    nav_msgs/Odometry `odometry` topics (relative to each world's namespace) where recorded."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    try:
        stream = open(path, "rb")
    except OSError as e:
        raise ResimError(f"{path}: {e.strerror or e}") from None
    with stream:
        try:
            reader = make_reader(stream)
            metadata = [(m.name, dict(m.metadata)) for m in reader.iter_metadata()]
            metas = [meta for name, meta in metadata if name == METADATA]
            if not metas:
                raise ResimError(
                    f"{path} holds no physics inputs (recorded with --no-record-inputs, by a fleet over several devices, or before batchsim recorded "
                    "them): it cannot be re-run; record it again"
                )
            recorded = [w for meta in metas for w in json.loads(meta["worlds"])]
            chosen = list(recorded) if worlds is None else list(dict.fromkeys(worlds))
            missing = [w for w in chosen if w not in recorded]
            if missing:
                everything = next((json.loads(m["worlds"]) for name, m in metadata if name == "batchsim"), [])
                if missing[0] in everything:
                    raise ResimError(f"{path} recorded world {missing[0]} without its inputs (a fleet over several devices): it cannot be re-run")
                raise ResimError(f"{path} does not hold world {missing[0]} (it recorded worlds {_ranges(recorded)})")
            attachments = {a.name: a.data for a in reader.iter_attachments()}
            out = []
            for meta in metas:
                names = resim_names(meta.get("group", ""))
                model = attachments.get(names.model)
                if model is None or model_hash(model) != meta["model_sha256"]:
                    raise ResimError(f"{path}: its model attachment {names.model} is missing or does not match its hash")
                theirs = json.loads(meta["worlds"])
                mine = [w for w in chosen if w in theirs]
                if not mine:
                    continue
                namespaces = json.loads(meta["namespaces"])
                rows = {w: theirs.index(w) for w in mine}
                namespaces_of = {w: namespaces[theirs.index(w)] for w in mine}
                layout = InputsLayout.from_json(meta["layout"])
                out.append(_read_messages(reader, meta, layout, model, rows, namespaces_of, tf, tuple(odometry), names))
            return out
        except (McapError, ValueError, KeyError, EOFError) as e:
            raise ResimError(f"{path}: not a readable batchsim recording ({e})") from None


def _read_messages(
    reader, meta, layout: InputsLayout, model: bytes, rows: dict[int, int], namespaces: dict[int, str], tf: bool,
    odometry: tuple[str, ...], names: ResimNames,
) -> Recorded:
    from mcap_ros2.decoder import DecoderFactory

    js_topics = _joint_state_topics(reader, namespaces)  # topic -> (world, the joint names' prefix)
    worlds = list(rows)
    picked = np.array([rows[w] for w in worlds], np.intp)
    headers: list[np.ndarray] = []
    inputs: list[np.ndarray] = []
    starts: dict[int, list[Start]] = {w: [] for w in worlds}
    states: dict[str, list] = {t: [] for t in js_topics}
    decoders: dict[int, object] = {}
    factory = DecoderFactory()
    events: list[dict] = []
    prefixes = {f"{ns.strip('/')}/": w for w, ns in namespaces.items()}
    transforms: dict[int, list] = {w: [] for w in worlds}
    odom_topics = {_topic(ns, t): (w, t) for w, ns in namespaces.items() for t in odometry}
    odoms: dict[tuple[int, str], list] = {key: [] for key in odom_topics.values()}
    topics = [names.inputs, names.starts, names.events, *js_topics, *odom_topics, *(["/tf"] if tf else [])]
    for schema, channel, message in reader.iter_messages(topics=topics):
        if channel.topic == names.inputs:
            header, values = unpack(message.data)
            headers.append(header)
            inputs.append(values[picked])
        elif channel.topic == names.starts:
            header, values = unpack(message.data)
            for row in values:
                world, draw, fresh, state, params = layout.split_start(row)
                if world in starts:
                    starts[world].append(Start(int(header[0]), state.copy(), draw, params, fresh))
        elif channel.topic == names.events:
            events.append(json.loads(unpack_string(message.data)))
        elif channel.topic in odom_topics:
            decode = decoders.get(channel.id)
            if decode is None:
                decode = decoders[channel.id] = factory.decoder_for(channel.message_encoding, schema)
            m = decode(message.data)
            p, q, v, a = m.pose.pose.position, m.pose.pose.orientation, m.twist.twist.linear, m.twist.twist.angular
            stamp = message_ns(m.header.stamp)
            odoms[odom_topics[channel.topic]].append((stamp, (p.x, p.y, p.z, q.x, q.y, q.z, q.w, v.x, v.y, v.z, a.x, a.y, a.z)))
        elif channel.topic == "/tf":
            decode = decoders.get(channel.id)
            if decode is None:
                decode = decoders[channel.id] = factory.decoder_for(channel.message_encoding, schema)
            _split_tf(decode(message.data), prefixes, transforms)
        else:
            decode = decoders.get(channel.id)
            if decode is None:
                decode = decoders[channel.id] = factory.decoder_for(channel.message_encoding, schema)
            states[channel.topic].append((message.log_time, decode(message.data)))
    if not headers:
        raise ResimError(f"it holds no {names.inputs} messages: nothing to re-run")
    order = np.argsort([h[0] for h in headers], kind="stable")
    stacked = np.stack(inputs)[order]  # (nperiod, nworld, width)
    out = {}
    for k, w in enumerate(worlds):
        joint_states = [_joint_states(states[t], prefix) for t, (v, prefix) in js_topics.items() if v == w and states[t]]
        out[w] = WorldRecord(
            w, namespaces[w], sorted(starts[w], key=lambda s: s.period), stacked[:, k], joint_states,
            _tf_states(transforms[w]) if tf else None,
            {t: _series(odoms[(w, t)]) for t in odometry if odoms[(w, t)]},
        )  # fmt: skip
    events.sort(key=lambda e: e["period"])
    return Recorded(meta, layout, model, np.stack(headers)[order], out, events, meta.get("group", ""))


def _topic(namespace: str, topic: str) -> str:
    """A world's topic as the bridge names it: `/<ns>/<topic>`, or `/<topic>` at the root."""
    ns = namespace.strip("/")
    return f"/{ns}/{topic.strip('/')}" if ns else f"/{topic.strip('/')}"


def _joint_state_topics(reader, namespaces: dict[int, str]) -> dict[str, tuple[int, str]]:
    """The recorded sensor_msgs/JointState topics of the worlds asked for -> (world, prefix): a
    world's own `<ns>/joint_states` (prefix ""), and in a world of several robots each robot's
    `<ns>/<robot>/joint_states`, whose joints the model names `<robot>/<joint>`."""
    summary = reader.get_summary()
    channels = summary.channels.values() if summary is not None else ()
    roots = {_topic(ns, ""): w for w, ns in namespaces.items()}  # "/world_3/" -> 3
    out = {}
    for channel in channels:  # once each, whatever the worlds asked (a 1024-world file has thousands)
        head = channel.topic.removesuffix("joint_states")
        if head == channel.topic:
            continue
        if head in roots:  # <ns>/joint_states
            out[channel.topic] = (roots[head], "")
            continue
        root, _, robot = head[:-1].rpartition("/")  # <ns>/<robot>/joint_states
        if robot and f"{root}/" in roots:
            out[channel.topic] = (roots[f"{root}/"], f"{robot}/")
    return out


def _series(rows: list) -> tuple[np.ndarray, np.ndarray]:
    rows.sort(key=lambda r: r[0])
    return np.array([r[0] for r in rows], np.int64), np.array([r[1] for r in rows], np.float64)


def _split_tf(msg, prefixes: dict[str, int], out: dict[int, list]) -> None:
    """A /tf message's transforms, per world asked for (by its frames' namespace prefix)."""
    per: dict[int, list] = {}
    stamp = None
    for t in msg.transforms:
        head, _, child = t.child_frame_id.partition("/")
        w = prefixes.get(head + "/")
        if w is None:
            continue
        stamp = message_ns(t.header.stamp)
        r, v = t.transform.rotation, t.transform.translation
        per.setdefault(w, []).append((t.header.frame_id.partition("/")[2], child, (v.x, v.y, v.z, r.x, r.y, r.z, r.w)))
    for w, rows in per.items():
        out[w].append((stamp, rows))


def _tf_states(messages: list) -> TfStates | None:
    if not messages:
        return None
    messages.sort(key=lambda m: m[0])
    pairs = [(parent, child) for parent, child, _ in messages[0][1]]
    values = np.array([[v for _, _, v in rows] for _, rows in messages], np.float64)
    return TfStates(np.array([m[0] for m in messages], np.int64), pairs, values)


def _joint_states(messages: list, prefix: str) -> JointStates:
    """A topic's JointState messages as arrays (the first message's joint order), its joint names
    prefixed as the model names them."""
    messages.sort(key=lambda m: m[0])
    names = [prefix + n for n in messages[0][1].name]
    stamps = np.array([message_ns(m.header.stamp) for _, m in messages], np.int64)
    position = np.array([list(m.position) for _, m in messages], np.float64).reshape(len(messages), -1)
    velocity = np.array([list(m.velocity) or [np.nan] * len(names) for _, m in messages], np.float64).reshape(len(messages), -1)
    effort = np.array([list(m.effort) or [np.nan] * len(names) for _, m in messages], np.float64).reshape(len(messages), -1)
    return JointStates(stamps, names, position, velocity, effort)


def _ranges(worlds: Sequence[int]) -> str:
    """[0, 1, 2, 5] -> '0-2,5'."""
    out, ws = [], sorted(worlds)
    i = 0
    while i < len(ws):
        j = i
        while j + 1 < len(ws) and ws[j + 1] == ws[j] + 1:
            j += 1
        out.append(f"{ws[i]}" if i == j else f"{ws[i]}-{ws[j]}")
        i = j + 1
    return ",".join(out)
