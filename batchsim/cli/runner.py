"""`batchsim`: build the fleet, its controllers and bridge, run the loop with a status line."""

from __future__ import annotations

import argparse
import dataclasses
import math
import re
import shutil
import signal
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any, TextIO

import batchsim
from batchsim import startup
from batchsim.backends import Choice, backend_class, estimate_memory, resolve
from batchsim.cli import description_topic
from batchsim.cli.args import (
    UsageError,
    _load,
    check_args,
    run_parser,
    split_ros_args,
)  # fmt: skip
from batchsim.cli.bridge_flags import bridge_options, option_flag
from batchsim.contract import Contract
from batchsim.controllers import ControllerManager, default_controllers, load_controllers
from batchsim.controllers.robots import load_fleet_controllers
from batchsim.fleet.groups import Group
from batchsim.loop import LoopStats, OptionError, RateError, SimLoop, format_stats, whole_ratio
from batchsim.model import model_names
from batchsim.sensors import SensorConfig
from batchsim.types import ConfigurationError
from ros_bridge.options import BridgeOptions, default_workers


def build(
    args: argparse.Namespace, progress: startup.Progress | None = None, group: Group | None = None
) -> Contract:
    """The configured, active system: the model loaded, the memory checked, the worlds made; of
    one group of a fleet of several (batchsim.fleet.groups), numbered from its first world."""
    progress = progress if progress is not None else startup.Progress()
    nworld = args.worlds if group is None else group.worlds
    offset = args.world_offset + (0 if group is None else group.first_world)
    options: dict[str, Any] = {}
    for flag, option in (("threads", "nthread"), ("nconmax", "nconmax"), ("njmax", "njmax")):
        if getattr(args, flag) is not None:
            options[option] = getattr(args, flag)
    if args.deterministic:
        options["deterministic"] = True
    if args.log_dir is not None:  # else make() places it, away from the working directory
        batchsim.set_log_dir(args.log_dir)
    if args.devices is not None:
        names = [d.strip() for d in args.devices.split(",") if d.strip()]
        options["devices"] = "all" if names == ["all"] else [int(d) if d.isdigit() else d for d in names]
        options["processes"] = args.shards == "processes"
    sensors = SensorConfig.from_flags(
        args.sensors,
        camera_rate=args.camera_rate,
        lidar_rate=args.lidar_rate,
        camera_resolution=args.camera_resolution,
        seed=args.noise_seed,
    )
    with progress.stage(f"loading {args.fleet or args.model}" + (f" (group {group.name})" if group else "")):
        spec = _load(args) if group is None else batchsim.load_fleet(group.fleet)
    chosen, _ = resolve(args.backend, spec, nworld)
    if not args.skip_memory_check:
        check_memory(args, spec, chosen, nworld)
    with progress.stage(f"allocating {nworld} worlds on {chosen.value}" + (f" (group {group.name})" if group else "")):
        sim = batchsim.make(
            spec,
            nworld,
            args.backend,
            sensors=sensors,
            randomize=args.randomize,
            world_offset=offset,
            **options,
        )
        sim.configure()
        sim.activate()
    for warning in sim.sensors.config.warnings:  # plugins not run, params not taken: never dropped silently
        print(f"batchsim: warning: {warning}", file=sys.stderr, flush=True)
    return sim


def check_memory(args: argparse.Namespace, spec: batchsim.RobotSpec, backend: Choice, nworld: int | None = None) -> None:
    """Refuse (MemoryCheckError, one line) a fleet the estimate says will not fit; warn near the edge
    (`nworld` worlds: a group's; default --worlds)."""
    nworld = args.worlds if nworld is None else nworld
    cls = backend_class(backend)
    on_device, device_memory = False, None
    devices = getattr(cls, "available_devices", None)  # a backend that runs on devices says which
    if devices is not None:
        on_device = not str(devices()[0]).startswith("cpu")
        if on_device and args.devices is None:  # several devices: each holds a share, not checked
            device_memory = startup.device_memory(cls)
    estimate = estimate_memory(
        spec,
        backend,
        nworld,
        ros=not args.no_ros,
        ros_workers=args.bridge_workers if args.bridge_workers is not None else default_workers(nworld),
        nthread=args.threads,
        on_device=on_device,
        nconmax=args.nconmax,
        njmax=args.njmax,
        controllers=(args.controllers or "").lower() != "none",
    )
    if estimate is None:
        unchecked = f"the {backend.value} backend states no memory estimate: not checked"
        print(f"batchsim: warning: {unchecked}", file=sys.stderr, flush=True)
        return
    for warning in (startup.check_host_memory(estimate), startup.check_device_memory(estimate, device_memory)):
        if warning:
            print(f"batchsim: warning: {warning}", file=sys.stderr, flush=True)


def compile_programs(sim: Contract, loop: SimLoop, progress: startup.Progress) -> None:
    """mjx compiles, and warp captures, its program on the first control period, and its
    render and ray programs on the first image and scan: run one of each now, under a
    progress stage, and reset, so the first status line means the fleet runs (a rover
    fleet's cameras and lidars once stalled 26 s at their first request on a GPU)."""
    if not sim.compiles_first_period:
        return
    # sensors drawn in one batched launch (sensors_batched: warp's kernels) compile on first use;
    # the others (the host renderer) have nothing to compile, and every world would cost a render
    cameras, lidars = (list(sim.sensors.cameras), list(sim.sensors.lidars)) if sim.sensors_batched else ([], [])
    sensors = ", ".join(f"{len(v)} {k}{'s' if len(v) > 1 else ''}" for k, v in (("camera", cameras), ("lidar", lidars)) if v)
    with progress.stage(f"compiling {sim.name}'s program for {sim.nworld} worlds" + (f" and its {sensors}" if sensors else "")):
        sim.read(0.0, loop.period)
        sim.write(0.0, loop.period)
        sim.step(loop.substeps)
        for camera in cameras:  # on the device, every world, no noise drawn: the sensors' streams stay at their start
            sim.render(camera, device=True)
        for lidar in lidars:
            sim.scan(lidar, device=True)
        sim.reset()


def group_options(options: BridgeOptions, group: Group) -> BridgeOptions:
    """The bridge options of one group of a fleet of several: its worlds numbered from its first,
    /clock and the fleet's services the first group's alone, and its share of the one recording
    (the recorded worlds that are its; the first group's leads the others', ros_bridge/bridge.py's
    join_bridges, even where none of its worlds is recorded) and of the one view."""
    first = group.first_world
    record = options.record
    if record is not None:
        worlds = record.worlds  # the fleet's numbers: this group's, numbered from its first
        if worlds is not None:
            worlds = tuple(w - first for w in worlds if first <= w < first + group.worlds)
        record = dataclasses.replace(record, worlds=worlds, group=True) if worlds != () or first == 0 else None
    return dataclasses.replace(
        options,
        world_offset=options.world_offset + first,
        clock=options.clock and first == 0,
        fleet_services=first == 0,
        record=record,
    )


def setup_controllers(sim: Contract, args: argparse.Namespace) -> tuple[ControllerManager | None, float | None]:
    """The run's controllers and the control rate their YAML's update_rate asks for.

    --controllers names a controller_manager YAML; without it a shipped model gets its
    default (models/<name>.yaml), any other model none; `--controllers none` runs none.
    Every configuration error is raised here, before the loop starts.
    """
    source = args.controllers
    if source is not None and source.lower() == "none":
        return None, None
    if sim.spec.robots:  # a fleet: each robot's own YAML (batchsim.controllers.robots)
        manager = load_fleet_controllers(sim.spec, sim.nworld)
        return manager, _checked_rate(sim, args, manager)
    if source is None:
        if str(args.model) not in model_names():
            return None, None
        source = default_controllers(str(args.model))
        if source is None:
            return None, None
    manager = load_controllers(source, sim.spec, sim.nworld)
    return manager, _checked_rate(sim, args, manager)


def _checked_rate(sim: Contract, args: argparse.Namespace, manager: ControllerManager | None) -> float | None:
    """The manager's update_rate, once it is a whole number of physics steps."""
    rate = manager.update_rate if manager is not None else None
    if rate is not None and args.control_rate is None:
        try:
            whole_ratio(1.0 / sim.dt, rate)
        except RateError as e:
            raise ConfigurationError(
                f"{manager.source}: controller_manager: update_rate: {rate:g} Hz is not a whole number of "
                f"physics steps of {sim.dt:g} s (the model's timestep): {e.hint}"
            ) from None
    return rate


#: library option names whose flag is not `--<option with dashes>`


def start_ros(
    sim: Contract, loop: SimLoop, args: argparse.Namespace, manager: ControllerManager | None = None, group: Group | None = None
):
    """The ROS 2 bridge for this run (or this group of its worlds), serving `manager`'s controllers
    too (ros_bridge/bridge.py's BridgeParts), neither recording nor viewed yet: `join_ros` starts
    those once every group's bridge is up.

    Errors name the flags; another process already serving these worlds or /clock is a
    UsageError (exit 2) naming that process's node. A group's worlds are numbered from its first
    world; the first group's bridge alone publishes /clock and serves /batchsim/*."""
    try:
        from ros_bridge.bridge import ConflictKind, FleetConflict, WorkerError, open_bridge
    except ModuleNotFoundError as e:
        raise UsageError(
            f"ROS 2 is not installed ({e.name} is missing): {startup.install_command('ros')}, or pass --no-ros"
        ) from None
    options = bridge_options(args)
    if group is not None:
        options = group_options(options, group)
    from ros_bridge.interfaces import missing_line

    missing = missing_line()
    if missing:
        print(f"batchsim: {missing}", file=sys.stderr)
    try:
        return open_bridge(sim, loop, options, manager)
    except OptionError as e:
        raise UsageError(e.named(option_flag(e.option))) from None
    except FleetConflict as e:
        namespace = e.kind is ConflictKind.NAMESPACE
        hint = "--world-offset, --namespace or another ROS_DOMAIN_ID" if namespace else "--no-clock on all but one"
        raise UsageError(f"{e} ({hint})") from None
    except WorkerError as e:
        raise UsageError(str(e)) from None


def join_ros(batches: Sequence[Batch]) -> None:
    """Every batch's bridge recorded and viewed together (ros_bridge/bridge.py's join_bridges): the
    run's recording from its first period where --record names a file, and its view; a fleet of
    several groups in one file and one page."""
    from ros_bridge.bridge import join_bridges

    try:
        join_bridges([b.bridge for b in batches], [b.group.name if b.group is not None else "" for b in batches])
    except OptionError as e:
        for b in batches:  # refused: the bridges already up go now, not at exit
            b.bridge.host.close()
        raise UsageError(e.named(option_flag(e.option))) from None


def check_group_args(args: argparse.Namespace) -> None:
    """A fleet of groups' --record-worlds names the fleet's worlds: one it does not have is refused
    here, as a fleet of one group's bridge refuses it (each group's bridge sees only its own)."""
    worlds = args.record_worlds if args.groups is not None else None
    bad = [w for w in worlds or () if not 0 <= w < args.groups.nworld]
    if bad:
        raise UsageError(
            f"--record-worlds names world {bad[0]}, which this fleet does not have (worlds 0..{args.groups.nworld - 1})"
        )


def _interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def fit(line: str, width: int) -> str:
    """`line` in `width` characters (a terminal's, less one: a line that fills its last column
    wraps, and `\r` then redraws only the wrapped part, leaving a stale row each second): its
    parenthetical remarks dropped first, then cut, with an ellipsis."""
    if len(line) <= width:
        return line
    line = re.sub(r" \([^()]*\)", "", line)
    return line if len(line) <= width else line[: max(0, width - 1)] + "…"


class StatusLine:
    """The live status line of a run: redrawn in place on a terminal (the rest of the line
    cleared), one line per report in a log: every second on a terminal, every LOG_EVERY
    seconds in a log (a file or pipe), or `every` seconds. A paused loop reports nothing, so
    while it is paused a watcher thread draws `paused` once a second (once per pause in a log).

    Use as a context manager around `loop.run(status.report)`.
    """

    LOG_EVERY = 10.0

    def __init__(
        self,
        loop: SimLoop,
        nworld: int,
        backend: str,
        *,
        stream: TextIO | None = None,
        quiet: bool = False,
        every: float | None = None,
    ):
        self.loop = loop
        self.nworld = nworld
        self.backend = backend
        self.stream = stream if stream is not None else sys.stderr
        self.quiet = quiet
        self.tty = self.stream.isatty()
        self.every = every if every is not None else (1.0 if self.tty else self.LOG_EVERY)
        self._last = -math.inf
        self._lock = threading.Lock()
        self._drawn = False
        self._stop = threading.Event()
        self._watcher = threading.Thread(target=self._watch, name="batchsim-status", daemon=True)

    def report(self, stats: LoopStats) -> None:
        now = time.monotonic()
        if now - self._last < self.every - 0.05:  # the loop reports about every second
            return
        self._last = now
        self._draw(format_stats(stats, self.nworld, self.backend))

    def _draw(self, line: str) -> None:
        if self.quiet:
            return
        with self._lock:
            self.stream.write(f"\r{fit(line, shutil.get_terminal_size().columns - 1)}\x1b[K" if self.tty else line + "\n")
            self.stream.flush()
            self._drawn = True

    def _watch(self) -> None:
        shown = False
        while not self._stop.wait(1.0):
            if not self.loop.paused:
                shown = False
            elif self.tty or not shown:
                stats = dataclasses.replace(self.loop.stats, sim_time=self.loop.sim_time, paused=True)
                self._draw(format_stats(stats, self.nworld, self.backend))
                shown = True

    def __enter__(self) -> StatusLine:
        if not self.quiet:
            self._watcher.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        if self._watcher.is_alive():
            self._watcher.join()
        with self._lock:
            if self.tty and self._drawn:
                self.stream.write("\n")  # the next line starts below the status line
                self.stream.flush()


@dataclasses.dataclass
class Batch:
    """One batch of a run: its system (the run's; a group's, in a fleet of several groups), its
    controllers, its loop (the first batch's runs the others, SimLoop.join) and its bridge."""

    group: Group | None
    sim: Contract
    manager: ControllerManager | None
    loop: SimLoop
    bridge: Any = None  # ros_bridge/bridge.py's BridgeParts


def build_batch(args: argparse.Namespace, progress: startup.Progress, group: Group | None, first: Batch | None) -> Batch:
    """The system, controllers and loop of the run (or of one group, its loop joined to the
    first group's); the bridge is started by the caller once every loop is joined."""
    sim = build(args, progress, group)
    manager, update_rate = setup_controllers(sim, args)
    control_rate = args.control_rate if args.control_rate is not None else update_rate
    try:
        loop = SimLoop(
            sim,
            control_rate=control_rate if control_rate is not None or first is None else first.loop.control_rate,
            rtf=args.rtf,
            duration=args.duration,
            thread_priority=args.thread_priority,
            cpu_affinity=args.cpu_affinity,
        )
        if first is not None:
            first.loop.join(loop)
    except OptionError as e:
        raise UsageError(e.named(option_flag(e.option))) from None
    if manager is not None:
        for warning in manager.warnings:
            print(f"batchsim: warning: {warning}", file=sys.stderr)
    compile_programs(sim, loop, progress)
    return Batch(group, sim, manager, loop)


def run(argv: Sequence[str]) -> int:
    # until the loop runs, SIGTERM ends the start as Ctrl-C does: what was started (bridge
    # workers, shared memory) is stopped and removed on the way out
    signal.signal(signal.SIGTERM, _interrupt)
    argv, ros_args = split_ros_args(argv)
    args = run_parser().parse_args(argv)
    args.ros_args = ros_args
    progress = startup.Progress(sys.stderr)
    with startup.StartupGuard(progress):
        description_topic.fetch(args, progress)
    check_args(args)
    check_group_args(args)
    batches: list[Batch] = []
    with startup.StartupGuard(progress):
        for group in args.groups.groups if args.groups is not None else (None,):
            batches.append(build_batch(args, progress, group, batches[0] if batches else None))
        for b in batches:
            if not args.no_ros:
                named = f" of group {b.group.name}" if b.group is not None else ""
                with progress.stage(f"creating ROS 2 endpoints for {b.sim.nworld} worlds{named}"):
                    b.bridge = start_ros(b.sim, b.loop, args, b.manager, b.group)
            if b.manager is not None and b.manager not in b.loop.participants:
                b.loop.participants.append(b.manager)
        if not args.no_ros:
            join_ros(batches)
    loop, first = batches[0].loop, batches[0].sim

    def on_signal(signum: int, frame: Any) -> None:
        loop.stop()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)

    backend = f"{first.name} ({first.reason})"
    print(f"batchsim: {_what(batches, loop, args)}", file=sys.stderr, flush=True)
    try:
        with StatusLine(loop, loop.nworld, backend, quiet=args.quiet, every=args.status_every) as status:
            stats = loop.run(status.report)
    finally:
        for b in batches:
            if b.bridge is not None:
                b.bridge.host.close()
            b.sim.shutdown()
    print(
        f"batchsim: stopped at sim time {loop.sim_time:.3f} s; last: {format_stats(stats, loop.nworld, backend)}",
        file=sys.stderr,
        flush=True,
    )
    return 0


def _what(batches: list[Batch], loop: SimLoop, args: argparse.Namespace) -> str:
    """The run's first line: what runs where, at what rate, and its namespaces and controllers."""
    first = batches[0].sim
    rtf = "max" if args.rtf == 0 else f"{args.rtf:g}"
    where = f"on {first.name} ({first.reason}), control {loop.control_rate:g} Hz ({loop.substeps} x {first.dt:g} s), rtf {rtf}"

    def served(b: Batch) -> str:
        return ("" if b.bridge is None else f", ROS 2 namespaces {b.bridge.host.describe()}") + (
            "" if b.manager is None else f", controllers {', '.join(b.manager.controllers) or 'none'}"
        )

    if len(batches) == 1:
        b = batches[0]
        return f"{b.sim.nworld} x {b.sim.spec.name} {where}{served(b)}"
    groups = "; ".join(f"group {b.group.name}: {b.sim.nworld} x {b.sim.spec.name}{served(b)}" for b in batches if b.group)
    return f"{loop.nworld} worlds in {len(batches)} groups {where}; {groups}"


#: the errors a command line, a file or the machine causes (each one line naming its cause)
