"""Recording the fleet into one MCAP file: what is recorded (`RecordSpec`, part of the plan)
and the physics side (`Recording`, a loop participant). No rclpy here.

The file is written by one recorder process (ros_bridge/worker/recorder.py), not by the
bridge workers: one file needs one writer, and a process of its own keeps the file's
compression off both the loop and the workers' publishing. It never goes through DDS: the
loop's participant copies each snapshot's recorded rows into a ring in shared memory
(ros_bridge/protocol/recording.py), and the recorder serializes them with the workers' own
CDR templates. A recording starts with `--record PATH` (before the first period) or
through `/batchsim/record` (std_srvs/SetBool, worker 0) while the fleet runs, and ends with
the run, the service, or a failure of its own (a full disk: one line; the loop goes on).

Cameras and lidars are opt-in (`--record-topics front_camera/image_raw,scan,...`): while a
recording runs, their recorded topics are wanted for the recorded worlds as a subscriber
would want them (`Recording.want_sensors`, asked by sensor_topics.py's SensorFeed), and the
recorder reads the sensor blocks itself (ros_bridge/worker/sensor_recording.py).

A fleet of several groups of worlds (batchsim.fleet.groups) is one recording too: each group's
bridge has its own plan, shared memory and ring, and the first group's `Recording` leads the
others' (`lead`): it starts and stops the one recorder and their rings with its own, answers the
service, and hands the recorder every group's plan, which writes them all into one file.
"""

from __future__ import annotations

import dataclasses
import os
import pickle
import select
import subprocess
import sys
import time as wallclock
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path

import numpy as np

from batchsim.loop import OptionError, Participant, SimLoop
from batchsim.resim.layout import InputsLayout
from ros_bridge.input_recording import InputRecording
from ros_bridge.options import RecordOptions
from ros_bridge.outputs import OutputSpec
from ros_bridge.protocol.input_ring import INPUTS, STARTS, event_arrays, ring_arrays
from ros_bridge.protocol.recording import (
    RecordWriter,
    put_answer,
    recording,
    recording_arrays,
    set_recording,
    take_request,
)
from ros_bridge.sensor_topics import SensorPlan
from ros_bridge.throttle import how_ended
from ros_bridge.view_plan import recording_geometry

FLEET_TOPICS = ("/tf", "/tf_static", "/clock", "/diagnostics")
DESCRIPTION = "robot_description"
READY_TIMEOUT = 60.0  # s the recorder may take to come up (imports, templates) with --record
FINISH_TIMEOUT = 30.0  # s the recorder may take to drain the ring and close the file at the end
WATCH = 0.25  # s between two looks at the recorder process
# s after which a request is dropped: well inside the service's wait (SERVICE_WAIT), so a request
# carried out is answered in time, and one answered "did not answer in time" never runs later
STALE_REQUEST = 1.0


@dataclasses.dataclass(frozen=True)
class RecordSpec:
    """What a recording writes. Attributes: `outputs`, indices into the plan's outputs;
    `tf`, `tf_static`, `clock`, `description`, `diagnostics`: the fleet's /tf, /tf_static,
    /clock, each world's robot_description, and the worlds' status as /diagnostics;
    `worlds`, the recorded worlds (indices); `channels` and
    `widths`, the snapshot channels the ring copies; `path`, the file to record into from
    the start (None: on request only)."""

    outputs: tuple[int, ...]
    tf: bool
    tf_static: bool
    clock: bool
    description: bool
    worlds: tuple[int, ...]
    channels: tuple[int, ...]
    widths: tuple[int, ...]
    path: str | None = None
    # per camera and lidar (sensors.want's columns), the WANT_* bits of its recorded topics; () for none
    sensors: tuple[int, ...] = ()
    diagnostics: bool = False
    # a group's (RecordOptions.group): the topics named that this group does not publish
    unknown: tuple[str, ...] = ()
    # what re-simulation needs recorded every period (batchsim.resim); None: not recorded
    inputs: InputsLayout | None = None

    def arrays(self, nchannel: int) -> list[tuple[str, tuple[int, ...], str]]:
        arrays = recording_arrays(nchannel, len(self.worlds), self.channels, self.widths)
        if any(self.sensors):  # the seq the recorder took last (protocol/sensor_blocks.py)
            arrays.append(("rec.sensors.seen", (len(self.worlds), len(self.sensors)), "i8"))
        if self.inputs is not None:  # every period's inputs, and the worlds' (re)starts: protocol/input_ring.py
            nrow = len(self.worlds)
            arrays += ring_arrays(INPUTS, nrow, self.inputs.input_width)
            arrays += ring_arrays(STARTS, 1, self.inputs.start_width, least=max(256, 4 * nrow))
            arrays += event_arrays()
        return arrays


def record_spec(
    options: RecordOptions,
    outputs: Sequence[OutputSpec],
    widths: Sequence[int],
    tf_channel: int | None,
    clock: bool,
    nworld: int,
    sensors: SensorPlan | None = None,
) -> RecordSpec:
    """The recording `options` ask for; OptionError naming `record_topics` or `record_worlds`.
    Cameras' and lidars' topics (`sensors`) only where `options.topics` names them. A group of a
    fleet of several (`options.group`) keeps the names it does not publish in `unknown`, and
    without a world of its own records the fleet's /clock alone."""
    by_name = {o.topic.strip("/"): i for i, o in enumerate(outputs)}
    by_sensor = {t.name: t for t in sensors.topics()} if sensors is not None else {}
    fleet = [t for t in FLEET_TOPICS if t != "/clock" or clock]
    if tf_channel is None:
        fleet = [t for t in fleet if not t.startswith("/tf")]
    names = [*by_name, *fleet, *([DESCRIPTION] if tf_channel is not None else [])]
    unknown: list[str] = []
    if options.topics is None:
        chosen = [n for n, i in by_name.items() if not outputs[i].on_request] + [
            n for n in names if n not in by_name
        ]
    else:
        chosen = []
        for topic in options.topics:
            name = topic.strip()
            key = f"/{name.strip('/')}" if f"/{name.strip('/')}" in fleet else name.strip("/")
            if key not in names and key not in by_sensor and options.group:
                unknown.append(name)  # another group's, maybe: join_bridges asks them all
                continue
            if key not in names and key not in by_sensor:
                raise OptionError(
                    "record_topics",
                    f"names {topic!r}, which this fleet does not publish (topics: {', '.join([*names, *by_sensor])})",
                )
            chosen.append(key)
    worlds = tuple(range(nworld)) if options.worlds is None else tuple(dict.fromkeys(options.worlds))
    bad = [w for w in worlds if not 0 <= w < nworld]
    if bad:
        raise OptionError(
            "record_worlds", f"names world {bad[0]}, which this fleet does not have (worlds 0..{nworld - 1})"
        )
    if not worlds and not options.group:
        raise OptionError("record_worlds", "names no world")
    if not worlds:  # a fleet's first group, none of whose worlds is recorded: it leads, with /clock
        chosen = [n for n in chosen if n == "/clock"]
    picked = tuple(by_name[n] for n in chosen if n in by_name)
    channels = sorted(
        {f.channel for i in picked for f in outputs[i].fields} | ({tf_channel} if "/tf" in chosen else set())
    )
    bits = [0] * (sensors.nsensor if sensors is not None else 0)
    for name in chosen:
        if name in by_sensor:
            bits[by_sensor[name].sensor] |= by_sensor[name].want
    return RecordSpec(
        outputs=picked,
        tf="/tf" in chosen,
        tf_static="/tf_static" in chosen,
        clock="/clock" in chosen,
        description=DESCRIPTION in chosen,
        diagnostics="/diagnostics" in chosen,
        worlds=worlds,
        channels=tuple(channels),
        widths=tuple(widths[c] for c in channels),
        path=options.path,
        sensors=tuple(bits) if any(bits) else (),
        unknown=tuple(unknown),
    )


def default_path(now: datetime | None = None) -> str:
    """`batchsim_<date>-<time>.mcap` in the working directory, as `ros2 bag record` names its bags."""
    return f"batchsim_{(now or datetime.now()).strftime('%Y_%m_%d-%H_%M_%S')}.mcap"


def path_problem(path: str) -> str | None:
    """Why `path` cannot be recorded into, or None."""
    p = Path(path)
    if p.is_dir():
        return f"{path} is a directory"
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        return f"{path}: directory {parent} does not exist"
    if p.is_file():  # (a device, /dev/null or a pipe, is written to)
        return f"{path} exists; batchsim never records over a file (remove it, or name another)"
    if not os.access(parent, os.W_OK):
        return f"{path}: not writable"
    return None


class Recording(Participant):
    """The loop's side of recording: the ring writer, the recorder process, the service's mailbox.

    Args:
      plan: the fleet's plan (its `recording` says what is recorded).
      memory: the shared arrays (the recorder attaches to them).
      loop: the loop (with `rtf` 0, a full ring waits for the recorder rather than drop periods).

    In a fleet of several groups, the first group's recording leads the others' (`lead`): a
    follower only fills its ring, which its leader starts and stops, and waits on its leader's
    recorder where it waits.
    """

    def __init__(self, plan, memory, loop: SimLoop):
        self.plan = plan
        self.spec: RecordSpec = plan.recording
        self.memory = memory
        self.loop = loop
        self.writer = RecordWriter(memory, self.spec.channels, np.array(self.spec.worlds, dtype=np.intp))
        self.path: str | None = None
        self._proc: subprocess.Popen | None = None
        self._status: int | None = None  # the recorder's status pipe (read end)
        self._buffer = b""
        self._answered = 0
        self._used: set[str] = set()
        self._said = False  # the recorder said how it ended
        self._ready = False  # the recorder said it has the file open
        self._stopping = False  # asked to stop: the recorder is finishing the file
        self._geometry: bytes | None = None  # the robots' geoms, for the file (view_plan.py)
        self._next_watch = 0.0
        self._sensor_bits = np.array(self.spec.sensors, np.uint8)  # (nsensor,) or (0,)
        self._worlds = np.array(self.spec.worlds, np.intp)
        self._row = np.full(plan.nworld, -1, np.intp)  # per world, its row among the recorded
        self._row[self._worlds] = np.arange(len(self._worlds))
        self._leader: Recording = self
        self._followers: list[Recording] = []
        self._names: list[str] = [""]  # each group's name, this one's first ("": one group alone)
        # every period's physics inputs (batchsim.resim), where recorded
        self.inputs = InputRecording(plan, memory, loop, self.recorder_alive) if self.spec.inputs is not None else None

    # --- a fleet of several groups: one recording ---
    def lead(self, followers: Sequence[Recording], names: Sequence[str]) -> None:
        """Record `followers` (the other groups' recordings of a fleet of several) into this one's
        file: their rings start and stop with this one's and the recorder reads them all. `names`:
        every group's name, this one's first (the file names each group's geometry after it)."""
        if len(names) != 1 + len(followers):
            raise ValueError(f"lead: {len(names)} names for {1 + len(followers)} groups")
        self._followers, self._names = list(followers), list(names)
        for follower in followers:
            follower.follow(self)

    def follow(self, leader: Recording) -> None:
        """Be recorded by `leader`'s recorder (Recording.lead calls this)."""
        self._leader = leader

    def recorder_alive(self) -> bool:
        """Whether the recorder of this recording (of its leader, for a follower) runs; its status
        lines are read first, so a recorder that ended is seen."""
        lead = self._leader
        if lead._proc is not None:
            lead._watch(force=True)
        return lead._proc is not None

    def geometry(self) -> bytes | None:
        """The robots' geoms for the file (`batchsim view FILE`, view_plan.py); None without tf or worlds."""
        if self._geometry is None and self.plan.tf is not None and self.spec.worlds:
            self._geometry = recording_geometry(self.loop.sim, self.plan.tf)
        return self._geometry

    def _set_recording(self, on: bool) -> None:
        """Every ring of the recording (this one's and its followers') on, from the next period, or off."""
        for r in (self, *self._followers):
            if on:
                r.writer.restart()
                if r.inputs is not None:
                    r.inputs.restart()
                set_recording(r.memory, r.spec.channels)
            else:
                set_recording(r.memory, None)

    # --- start and stop ---
    def start(self, path: str, wait: bool = False) -> tuple[bool, str]:
        """Start the recorder into `path`; with `wait`, until it is ready (else it is, a moment later)."""
        if self._leader is not self:
            return False, "the fleet's first group records every group"
        if self._proc is not None:
            if self._stopping:  # the ring is the old recorder's until it has drained it
                return False, f"still finishing {self.path}: ask again in a moment"
            return False, f"already recording to {self.path}"
        problem = path_problem(path)
        if problem is not None:
            return False, f"cannot record: {problem}"
        read, write = os.pipe()
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "ros_bridge.worker.recorder", str(write)],
            stdin=subprocess.PIPE,
            pass_fds=(write,),
        )
        os.close(write)
        os.set_blocking(read, False)
        self._status, self._buffer, self.path, self._said, self._ready = read, b"", path, False, False
        self._used.add(path)
        # the rings take periods from now on, while the recorder comes up (a second or more):
        # a recording stopped before its recorder said ready still holds start..stop
        self._set_recording(True)
        groups = [(r.plan, r.geometry(), name) for r, name in zip((self, *self._followers), self._names, strict=True)]
        resim = [r.inputs.source(name) if r.inputs is not None else None for r, name in zip((self, *self._followers), self._names, strict=True)]
        self._proc.stdin.write(pickle.dumps((groups, os.path.abspath(path), resim)))
        self._proc.stdin.flush()
        if wait:
            deadline = wallclock.monotonic() + READY_TIMEOUT
            while (
                self._proc is not None and not self._ready and wallclock.monotonic() < deadline
            ):
                select.select([read], [], [], 0.1)
                self._watch()
        return True, f"recording to {path}"

    def stop(self, timeout: float = 0.0) -> tuple[bool, str]:
        """Stop writing into the ring and ask the recorder to finish the file (waiting up to `timeout` s)."""
        if self._proc is None:
            return False, "not recording"
        self._set_recording(False)
        self._stopping = True
        try:
            self._proc.stdin.close()  # EOF: drain the ring, write the summary, exit
        except OSError:
            pass
        path = self.path
        deadline = wallclock.monotonic() + timeout
        while self._proc is not None and wallclock.monotonic() < deadline:
            select.select([self._status], [], [], 0.1)
            self._watch()
        return True, f"stopped recording to {path}"

    def close(self) -> None:
        """End the run's recording: every period written gets into the file."""
        if self._proc is not None:
            self.stop(FINISH_TIMEOUT)
        if self._proc is not None:
            self._proc.kill()
            self._finished(
                f"batchsim: warning: recording: the recorder did not finish {self.path} in {FINISH_TIMEOUT:g} s"
            )

    # --- the loop thread ---
    def update(self, sim, time: float, period: float) -> None:
        self._serve()

    def while_stepping(self, sim, time: float, period: float) -> None:
        """This period's snapshot into the ring: after the host's (it runs first), which on a GPU
        writes it here too, beside the steps."""
        if not recording(self.memory):
            return
        if self.loop.rtf == 0:  # as fast as possible, every period: as fast as the recorder takes them
            while self.writer.full() and self.recorder_alive():
                wallclock.sleep(0.0005)
        self.writer.put_newest()

    def after_write(self, sim, time: float, period: float) -> None:
        if self.inputs is not None and recording(self.memory):
            self.inputs.after_write(sim, time, period)

    def on_reset(self, sim, worlds: np.ndarray | None) -> None:
        if self.inputs is not None:
            self.inputs.on_reset(worlds)

    def idle(self, sim, time: float) -> None:
        self._serve()
        if recording(self.memory):
            self.writer.put_newest()

    # --- cameras and lidars (sensor_topics.py's SensorFeed asks, in the loop thread) ---
    def want_sensors(self, want: np.ndarray) -> None:
        """While recording, OR the recorded camera and lidar topics' WANT bits into the
        recorded worlds' rows of `want` ((nworld, nsensor), the workers' want bits)."""
        if self._sensor_bits.any() and recording(self.memory):
            want[self._worlds] |= self._sensor_bits

    def hold_sensor(self, column: int, seq: np.ndarray, worlds: np.ndarray) -> None:
        """Before a sample of sensor `column` overwrites `worlds`' rows of its block (`seq`, the
        block's (nworld,) seqlock): with `--rtf 0`, wait until the recorder took the last one."""
        if self.loop.rtf != 0 or not self._sensor_bits.any() or not self._sensor_bits[column]:
            return
        rows = self._row[worlds]
        rows = rows[rows >= 0]
        seen = self.memory["rec.sensors.seen"]
        while (
            recording(self.memory)
            and (seq[self._worlds[rows]] != seen[rows, column]).any()
            and self.recorder_alive()
        ):
            wallclock.sleep(0.0005)

    def _serve(self) -> None:
        if self._leader is not self:  # the service is the leader's (the first group's worker 0)
            return
        request = take_request(self.memory, self._answered)
        if request is not None:
            ticket, on, age = request
            if age > STALE_REQUEST:  # its service answered "did not answer in time": nothing starts or stops
                ok, message = False, f"a request {age:.1f} s old (the loop was starting or busy) was dropped"
            else:
                ok, message = self.start(self._next_path()) if on else self.stop()
            put_answer(self.memory, ticket, ok, message)
            self._answered = ticket
        if self._proc is not None:
            self._watch()

    def _next_path(self) -> str:
        """--record's path the first time, then numbered beside it (`run_2.mcap`, ...); else a
        dated name. Never a name this run used or a file that exists (an earlier run's)."""
        base = self.spec.path or default_path()
        stem, suffix = os.path.splitext(base)
        path, k = base, 2
        while path in self._used or os.path.isfile(path):
            path, k = f"{stem}_{k}{suffix}", k + 1
        return path

    def _watch(self, force: bool = False) -> None:
        """The recorder's status lines; its end."""
        now = wallclock.monotonic()
        if not force and now < self._next_watch:
            return
        self._next_watch = now + WATCH
        ended = self._proc.poll() is not None  # before reading: its last lines are in the pipe then
        try:
            self._buffer += os.read(self._status, 65536)
        except OSError:  # BlockingIOError: nothing new
            pass
        *lines, self._buffer = self._buffer.split(b"\n")
        for line in lines:
            text = line.decode(errors="replace")
            if text == "ready":
                self._ready = True
            elif text:
                self._said = True
                print(f"batchsim: {text}", file=sys.stderr, flush=True)
        if ended:
            code = self._proc.returncode
            silent = f"batchsim: warning: recording: the recorder {how_ended(code)}; {self.path} holds what it wrote"
            self._finished(None if self._said else silent + " up to its last complete chunk")

    def _finished(self, line: str | None) -> None:
        self._set_recording(False)
        if line:
            print(line, file=sys.stderr, flush=True)
        if self._status is not None:
            os.close(self._status)
        self._proc, self._status, self._stopping = None, None, False
