"""The `batchsim` command.

    batchsim --worlds 16                     16 arms, over ROS 2, in real time
    batchsim --worlds 64 --model quadruped --rtf 0 --no-ros
    batchsim --worlds 16 --controllers controllers.yaml   ros2_control controllers in every world
    batchsim info arm                        interfaces and sensors of a model

Errors a user can fix (a missing file, malformed XML, an unknown model, a bad flag, a
fleet that will not fit in memory) print one line and exit with code 2. Start-up stages
that take over a second show progress. Ctrl-C or SIGTERM during start-up exits promptly
with one line and code 130 or 143 (nothing ran); once the run has begun they end it
cleanly with code 0.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.metadata
import math
import os
import platform
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

import mujoco

import batchsim
from batchsim import startup
from batchsim.backends import Backend, BackendUnavailable, backend_class, resolve
from batchsim.controllers import ControllerManager, default_controllers, load_controllers
from batchsim.hardware import BatchedSystem, ConfigurationError, LifecycleError
from batchsim.loop import LoopStats, OptionError, RateError, SimLoop, format_stats, whole_ratio
from batchsim.model import ModelError, model_names
from batchsim.model.description import model_file, read_description
from batchsim.model.from_urdf import is_urdf
from batchsim.model.params import ParamsError
from batchsim.sensors import DeclarationError, SensorConfig, SensorConfigError, SensorSuite
from batchsim.startup import MemoryCheckError

EXIT_USAGE = 2


class UsageError(Exception):
    """A problem the user can fix; printed as one line, exit code 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2, no usage dump
        raise UsageError(message)


def run_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="batchsim",
        description="Run N copies of one MuJoCo robot, each on its own ROS 2 namespace.",
        epilog="`batchsim info MODEL` lists a model's interfaces and sensors.",
    )
    p.add_argument("--worlds", type=int, default=16, help="number of worlds (default 16)")
    p.add_argument(
        "--model",
        default=None,
        help="shipped model name or MJCF path (default: the --ros2-control file's mujoco_model param, else arm)",
    )
    p.add_argument(
        "--backend", default="auto", help="cpu, mjx, warp or auto (default auto: picked for the hardware)"
    )
    p.add_argument("--duration", type=float, default=None, help="stop after this many simulated seconds")
    p.add_argument("--rtf", type=float, default=1.0, help="real-time factor; 0 runs as fast as possible")
    p.add_argument("--control-rate", type=float, default=None, help="Hz: commands applied, state read")
    p.add_argument("--threads", type=int, default=None, help="cpu backend: worker threads (default: all cores)")
    p.add_argument(
        "--devices",
        default=None,
        help="mjx/warp: spread the worlds over several GPUs: all, or indices 0,1,... (default: one device)",
    )
    p.add_argument(
        "--shards",
        choices=("processes", "threads"),
        default="processes",
        help="with --devices: one process per device (default), or one thread per device in this process",
    )
    p.add_argument("--nconmax", type=int, default=None, help="warp backend: contacts per world to start with (default: sized from a CPU rollout; grows when it overflows)")
    p.add_argument("--njmax", type=int, default=None, help="warp backend: constraint rows per world to start with (default: sized likewise; grows likewise)")
    p.add_argument(
        "--deterministic",
        action="store_true",
        help="mjx/warp on a GPU: bitwise-repeatable runs, slower (cpu always is)",
    )
    p.add_argument("--ros2-control", default=None, help="URDF/XML file with a <ros2_control> block")
    _urdf_flags(p)
    p.add_argument(
        "--keyframe", default=None, help="keyframe (name or index) to start in (default: home, if the model has one)"
    )
    p.add_argument("--no-ros", action="store_true", help="run without the ROS 2 bridge")
    p.add_argument("--quiet", action="store_true", help="no live status line")
    p.add_argument(
        "--skip-memory-check",
        action="store_true",
        help="start even where the memory estimate says the fleet will not fit",
    )
    p.add_argument(
        "--log-dir",
        default=None,
        help="where MuJoCo's own log (MUJOCO_LOG.TXT) goes (default: $XDG_STATE_HOME/batchsim, "
        "never the working directory)",
    )
    p.add_argument("--version", action="version", version=version_line())
    ros = p.add_argument_group("ROS 2 bridge")
    ros.add_argument("--namespace", default="world_{i}", help="per-world namespace template (default world_{i})")
    ros.add_argument("--publish-rate", type=float, default=None, help="Hz for topics (default: the control rate)")
    ros.add_argument("--sensor-rate", type=float, default=None, help="Hz for sensors/<sensor> topics (default: the publish rate)")
    ros.add_argument("--lockstep", action="store_true", help="each period waits for every world's command")
    ros.add_argument("--lockstep-timeout", type=float, default=1.0, help="seconds a lockstep period waits")
    ros.add_argument("--qos-depth", type=int, default=None, help="queue depth (default 10, or the MJCF's)")
    ros.add_argument("--reliability", choices=("reliable", "best_effort"), default=None)
    ros.add_argument("--command-timeout", type=float, default=None, help="seconds without commands before a world goes safe")
    ros.add_argument(
        "--bridge-workers",
        type=int,
        default=None,
        help="processes serving ROS (default: 1 on 2 cores; else 0 up to 64 worlds, then one per 128 worlds, "
        "at most half the cores); 0: in the physics process",
    )
    ros.add_argument(
        "--world-offset", type=int, default=0, help="number of the first world, for a fleet over several processes or hosts"
    )
    ros.add_argument("--no-clock", action="store_true", help="do not publish /clock (another process of the fleet does)")
    ros.add_argument(
        "--all-topics",
        action="store_true",
        help="create every per-world topic at start (default: sensor, actuator and controller_state topics "
        "appear when someone subscribes or publishes)",
    )
    ros.add_argument(
        "--no-tf", action="store_true", help="publish no tf, tf_static or robot_description (default: every world's)"
    )
    sens = p.add_argument_group("cameras, lidars and sensor noise")
    sens.add_argument(
        "--sensors",
        action="append",
        metavar="FILE",
        help="mujoco_ros2_control plugin YAML and/or batchsim's `sensors:` block (noise, dense lidars); may repeat",
    )
    sens.add_argument("--camera-rate", type=float, default=None, help="Hz for camera images (default: the YAML's, else 5)")
    sens.add_argument("--lidar-rate", type=float, default=None, help="Hz for lidar scans (default: the YAML's, else 10)")
    sens.add_argument("--camera-resolution", default=None, metavar="WxH", help="every camera's image size (default: the MJCF's)")
    sens.add_argument("--noise-seed", type=int, default=None, help="sensor noise seed (default: the YAML's, else 0)")
    p.add_argument(
        "--controllers",
        default=None,
        help="ros2_control controller_manager YAML; none: no controllers (default: the shipped model's own)",
    )
    return p


def version_line() -> str:
    """`batchsim --version`: batchsim's and the engines' versions."""
    try:
        version = importlib.metadata.version("batchsim")
    except importlib.metadata.PackageNotFoundError:
        version = "unknown (not installed)"
    return f"batchsim {version} (mujoco {mujoco.__version__}, python {platform.python_version()})"


def info_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="batchsim info", description="List a model's interfaces and sensors.")
    p.add_argument("model", nargs="?", help="shipped model name or MJCF path (default: as batchsim's --model)")
    p.add_argument("--worlds", type=int, default=16, help="world count the backend choice is for")
    p.add_argument("--backend", default="auto")
    p.add_argument("--ros2-control", default=None)
    p.add_argument("--keyframe", default=None)
    _urdf_flags(p)
    p.add_argument("--mjcf", action="store_true", help="print the MJCF batchsim compiles (for a URDF: the one it generates)")
    p.add_argument("--sensors", action="append", metavar="FILE", help="as batchsim's --sensors: what it makes of them")
    return p


def _urdf_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--mujoco-inputs", default=None, metavar="FILE",
        help="URDF model: a <mujoco_inputs> file (actuators, sensors, cameras, lidars), as mujoco_ros2_control's --m",
    )  # fmt: skip
    p.add_argument("--scene", default=None, metavar="FILE", help="URDF model: an MJCF scene file to add (lights, floor)")


def _load(args: argparse.Namespace) -> batchsim.RobotSpec:
    return batchsim.load(
        args.model, ros2_control=args.ros2_control, keyframe=args.keyframe, mujoco_inputs=args.mujoco_inputs, scene=args.scene
    )


def info(argv: Sequence[str]) -> int:
    args = info_parser().parse_args(argv)
    args.model = default_model(args.model, args.ros2_control)
    sensors = SensorConfig.from_flags(args.sensors)
    spec = _load(args)
    if args.mjcf:
        print(spec.xml)
        return 0
    chosen, reason = resolve(args.backend, spec, args.worlds)
    m = spec.mjmodel
    keys = ", ".join(repr(k) if k else f"#{i}" for i, k in enumerate(spec.keyframes)) or "none"
    base = spec.floating_base
    out = [
        f"model      {spec.name}  ({spec.path or 'string'})",
        f"timestep   {m.opt.timestep:g} s   nq {m.nq}  nv {m.nv}  nu {m.nu}",
        f"backend    {chosen.value} for {args.worlds} worlds ({reason})",
        f"starts in  {spec.initial.source}   (keyframes: {keys})",
        f"base       {f'free joint {base.joint!r} of body {base.body!r}' if base else 'fixed (no floating base)'}",
    ]
    if spec.ros is not None:
        r = spec.ros
        out.append(
            f"mujoco.ros2 ros_namespace={r.ros_namespace!r} topic_queue_size={r.topic_queue_size} "
            f"topic_reliability={r.topic_reliability}"
        )
    out.append(f"\nstate interfaces ({len(spec.state)})")
    out += [f"  {i:3d}  {c.name}" for i, c in enumerate(spec.state)]
    out.append(f"\ncommand interfaces ({len(spec.commands)})")
    out += [f"  {i:3d}  {c.name:32s} actuator {c.actuator}{_how(c)}" for i, c in enumerate(spec.commands)]
    out += [
        f"       {mc.joint} mimics {mc.source} (x {mc.multiplier:g} + {mc.offset:g}) on actuator {mc.actuator}"
        for mc in spec.mimics
    ]
    out.append(f"\nsensors ({len(spec.sensors)})")
    out += [
        f"  {s.name:24s} {s.type:14s} dim {s.dim}  ({', '.join(s.fields)})" for s in spec.sensors
    ]
    suite = SensorSuite.build(spec, args.worlds, sensors)
    out += sensor_lines(suite)
    warnings = spec.warnings + suite.config.warnings
    if warnings:
        out.append("\nwarnings (not acted on)")
        out += [f"  {w}" for w in warnings]
    if spec.problems:
        out.append("\nproblems (configure will fail)")
        out += [f"  {p}" for p in spec.problems]
    print("\n".join(out))
    return 0


def sensor_lines(suite: SensorSuite) -> list[str]:
    """`batchsim info`'s cameras and lidars."""
    out = []
    if suite.cameras:
        out.append(f"\ncameras ({len(suite.cameras)})")
        out += [
            f"  {c.name:24s} {c.width}x{c.height}  fx {c.info.fx:.1f} fy {c.info.fy:.1f}  "
            f"-> {c.image_topic}, {c.depth_topic}, {c.info_topic}"
            for c in suite.cameras.values()
        ]
    if suite.lidars:
        out.append(f"\nlidars ({len(suite.lidars)})")
        out += [
            f"  {ld.name:24s} {ld.kind.value:11s} {ld.nrow}x{ld.ncol} rays from site {ld.site}, azimuth "
            f"{ld.angle_min:+.3f}..{ld.angle_max:+.3f} rad, range {ld.range_min:g}..{ld.range_max:g} m -> {ld.topic}"
            for ld in suite.lidars.values()
        ]
    return out


def _how(c: Any) -> str:
    """How a command interface reaches ctrl, where it is not a plain copy."""
    if c.pid is not None:
        return f"  (PID p={c.pid.p:g} i={c.pid.i:g} d={c.pid.d:g})"
    if c.scale != 1.0 or c.offset != 0.0:
        return f"  (ctrl = {c.scale:g} x command + {c.offset:g})"
    return ""


_POSITIVE = {  # flag: what its number is, for the message; each must be finite and > 0
    "duration": "a finite number of simulated seconds",
    "control_rate": "a finite number",
    "publish_rate": "a finite number",
    "sensor_rate": "a finite number",
    "camera_rate": "a finite number",
    "lidar_rate": "a finite number",
    "lockstep_timeout": "a finite number of seconds",
    "command_timeout": "a finite number of seconds",
}
_AT_LEAST_ONE = ("worlds", "threads", "nconmax", "njmax", "qos_depth")
MAX_DOMAIN_ID = 232  # ROS 2's limit: DDS computes UDP ports from the domain id


def check_args(args: argparse.Namespace) -> None:
    """Every flag value the run will use, checked before anything starts.

    Raises:
      UsageError: the first bad value, as one line naming the flag and the value.
    """
    for name, what in _POSITIVE.items():
        value = getattr(args, name)
        if value is not None and not (math.isfinite(value) and value > 0):
            raise UsageError(f"--{name.replace('_', '-')} must be {what} > 0, got {value}")
    if not (math.isfinite(args.rtf) and args.rtf >= 0):
        raise UsageError(f"--rtf must be a finite number >= 0 (0: as fast as possible), got {args.rtf}")
    for name in _AT_LEAST_ONE:
        value = getattr(args, name)
        if value is not None and value < 1:
            raise UsageError(f"--{name.replace('_', '-')} must be >= 1, got {value}")
    args.model = default_model(args.model, args.ros2_control)
    model = Path(args.model).expanduser()
    if str(args.model) not in model_names() and model.is_dir():
        raise UsageError(f"--model {args.model}: is a directory, not an MJCF file")
    if args.log_dir is not None:
        try:
            batchsim.set_log_dir(args.log_dir)
        except ValueError as e:
            raise UsageError(f"--log-dir: {e}") from None
    if not args.no_ros:
        from ros_bridge.naming import DEFAULT_TEMPLATE, world_namespaces  # no rclpy: the rules only

        domain = os.environ.get("ROS_DOMAIN_ID", "").strip()
        if domain and not (domain.isdigit() and int(domain) <= MAX_DOMAIN_ID):
            raise UsageError(
                f"ROS_DOMAIN_ID={domain}: must be an integer in 0..{MAX_DOMAIN_ID} (DDS's ports run out above it; "
                "0..101 keeps clear of Linux's ephemeral ports), or unset (0)"
            )

        if args.namespace != DEFAULT_TEMPLATE:
            try:
                world_namespaces(args.worlds, args.namespace)
            except ValueError as e:  # NamingError; an OptionError names its flag through named()
                named = getattr(e, "named", None)
                raise UsageError(named("--namespace") if named else str(e)) from None


def default_model(model: str | None, ros2_control: str | None) -> str:
    """`--model`, else the --ros2-control file's `mujoco_model` param (as mujoco_ros2_control
    finds its simulation), else that file itself if it is a URDF (compiled to MJCF, as
    mujoco_ros2_control does without one), else the shipped arm."""
    if model is not None:
        return model
    if ros2_control is not None:
        found = model_file(read_description(ros2_control))
        if found is not None:
            return found
        if is_urdf(ros2_control):
            return ros2_control
    return "arm"


def build(args: argparse.Namespace, progress: startup.Progress | None = None) -> BatchedSystem:
    """The configured, active system: the model loaded, the memory checked, the worlds made."""
    progress = progress if progress is not None else startup.Progress()
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
    with progress.stage(f"loading {args.model}"):
        spec = _load(args)
    chosen, _ = resolve(args.backend, spec, args.worlds)
    if not args.skip_memory_check:
        check_memory(args, spec, chosen)
    with progress.stage(f"allocating {args.worlds} worlds on {chosen.value}"):
        sim = batchsim.make(spec, args.worlds, args.backend, sensors=sensors, **options)
        sim.configure()
        sim.activate()
    for warning in sim.sensors.config.warnings:  # plugins not run, params not taken: never dropped silently
        print(f"batchsim: warning: {warning}", file=sys.stderr, flush=True)
    return sim


def check_memory(args: argparse.Namespace, spec: batchsim.RobotSpec, backend: Backend) -> None:
    """Refuse (MemoryCheckError, one line) a fleet the estimate says will not fit; warn near the edge."""
    cls = backend_class(backend)
    on_device, device_memory = False, None
    if backend is not Backend.CPU:
        on_device = not str(cls.available_devices()[0]).startswith("cpu")
        if on_device and args.devices is None:  # several devices: each holds a share, not checked
            device_memory = startup.device_memory(cls)
    estimate = startup.estimate_memory(
        spec,
        backend.value,
        args.worlds,
        ros=not args.no_ros,
        nthread=args.threads,
        on_device=on_device,
        nconmax=args.nconmax,
        njmax=args.njmax,
        controllers=(args.controllers or "").lower() != "none",
    )
    for warning in (startup.check_host_memory(estimate), startup.check_device_memory(estimate, device_memory)):
        if warning:
            print(f"batchsim: warning: {warning}", file=sys.stderr, flush=True)


def compile_programs(sim: BatchedSystem, loop: SimLoop, progress: startup.Progress) -> None:
    """mjx compiles, and warp captures, its program on the first control period: run one
    now, under a progress stage, and reset, so the run starts compiled and at its start."""
    if sim.name not in (Backend.MJX.value, Backend.WARP.value):
        return
    with progress.stage(f"compiling {sim.name}'s program for {sim.nworld} worlds"):
        sim.read(0.0, loop.period)
        sim.write(0.0, loop.period)
        sim.step(loop.substeps)
        sim.reset()


def setup_controllers(sim: BatchedSystem, args: argparse.Namespace) -> tuple[ControllerManager | None, float | None]:
    """The run's controllers and the control rate their YAML's update_rate asks for.

    --controllers names a controller_manager YAML; without it a shipped model gets its
    default (models/<name>.yaml), any other model none; `--controllers none` runs none.
    Every configuration error is raised here, before the loop starts.
    """
    source = args.controllers
    if source is not None and source.lower() == "none":
        return None, None
    if source is None:
        if str(args.model) not in model_names():
            return None, None
        source = default_controllers(str(args.model))
        if source is None:
            return None, None
    manager = load_controllers(source, sim.spec, sim.nworld)
    rate = manager.update_rate
    if rate is not None and args.control_rate is None:
        try:
            whole_ratio(1.0 / sim.dt, rate)
        except RateError as e:
            raise ConfigurationError(
                f"{manager.source}: controller_manager: update_rate: {rate:g} Hz is not a whole number of "
                f"physics steps of {sim.dt:g} s (the model's timestep): {e.hint}"
            ) from None
    return manager, rate


#: library option names whose flag is not `--<option with dashes>`
_FLAGS = {"workers": "--bridge-workers"}


def _flag(option: str) -> str:
    return _FLAGS.get(option, "--" + option.replace("_", "-"))


def start_ros(sim: BatchedSystem, loop: SimLoop, args: argparse.Namespace, manager: ControllerManager | None = None):
    """The ROS 2 bridge for this run, serving `manager`'s controllers too.

    Errors name the flags; another process already serving these worlds or /clock is a
    UsageError (exit 2) naming that process's node."""
    try:
        from ros_bridge.bridge import BridgeOptions, FleetConflict, Reliability, WorkerError, start_bridge
    except ModuleNotFoundError as e:
        raise UsageError(
            f"ROS 2 is not installed ({e.name} is missing): {startup.install_command('ros')}, or pass --no-ros"
        ) from None
    options = BridgeOptions(
        namespace=args.namespace,
        publish_rate=args.publish_rate,
        sensor_rate=args.sensor_rate,
        qos_depth=args.qos_depth,
        reliability=Reliability(args.reliability) if args.reliability else None,
        command_timeout=args.command_timeout,
        lockstep=args.lockstep,
        lockstep_timeout=args.lockstep_timeout,
        workers=args.bridge_workers,
        world_offset=args.world_offset,
        clock=not args.no_clock,
        all_topics=args.all_topics,
        tf=not args.no_tf,
        description=args.ros2_control,
    )
    from ros_bridge.interfaces import missing_line

    missing = missing_line()
    if missing:
        print(f"batchsim: {missing}", file=sys.stderr)
    try:
        return start_bridge(sim, loop, options, manager)
    except OptionError as e:
        raise UsageError(e.named(_flag(e.option))) from None
    except FleetConflict as e:
        hint = (
            "--world-offset, --namespace or another ROS_DOMAIN_ID" if e.kind == "namespace" else "--no-clock on all but one"
        )
        raise UsageError(f"{e} ({hint})") from None
    except WorkerError as e:
        raise UsageError(str(e)) from None


def _interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


class StatusLine:
    """The live status line of a run: redrawn in place on a terminal (the rest of the line
    cleared), one line per report in a log. A paused loop reports nothing, so while it is
    paused a watcher thread draws `paused` once a second (once per pause in a log).

    Use as a context manager around `loop.run(status.report)`.
    """

    def __init__(
        self, loop: SimLoop, nworld: int, backend: str, *, stream: TextIO | None = None, quiet: bool = False
    ):
        self.loop = loop
        self.nworld = nworld
        self.backend = backend
        self.stream = stream if stream is not None else sys.stderr
        self.quiet = quiet
        self.tty = self.stream.isatty()
        self._lock = threading.Lock()
        self._drawn = False
        self._stop = threading.Event()
        self._watcher = threading.Thread(target=self._watch, name="batchsim-status", daemon=True)

    def report(self, stats: LoopStats) -> None:
        self._draw(format_stats(stats, self.nworld, self.backend))

    def _draw(self, line: str) -> None:
        if self.quiet:
            return
        with self._lock:
            self.stream.write(f"\r{line}\x1b[K" if self.tty else line + "\n")
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


def run(argv: Sequence[str]) -> int:
    # until the loop runs, SIGTERM ends the start as Ctrl-C does: what was started (bridge
    # workers, shared memory) is stopped and removed on the way out
    signal.signal(signal.SIGTERM, _interrupt)
    args = run_parser().parse_args(argv)
    check_args(args)
    progress = startup.Progress(sys.stderr)
    with startup.StartupGuard(progress):
        sim = build(args, progress)
        manager, update_rate = setup_controllers(sim, args)
        control_rate = args.control_rate if args.control_rate is not None else update_rate
        try:
            loop = SimLoop(sim, control_rate=control_rate, rtf=args.rtf, duration=args.duration)
        except OptionError as e:
            raise UsageError(e.named(_flag(e.option))) from None
        if manager is not None:
            for warning in manager.warnings:
                print(f"batchsim: warning: {warning}", file=sys.stderr)
        compile_programs(sim, loop, progress)
        bridge = None
        if not args.no_ros:
            with progress.stage(f"creating ROS 2 endpoints for {sim.nworld} worlds"):
                bridge = start_ros(sim, loop, args, manager)
        if manager is not None and manager not in loop.participants:
            loop.participants.append(manager)

    def on_signal(signum: int, frame: Any) -> None:
        loop.stop()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)

    backend = f"{sim.name} ({sim.reason})"
    print(
        f"batchsim: {sim.nworld} x {sim.spec.name} on {backend}, control {loop.control_rate:g} Hz "
        f"({loop.substeps} x {sim.dt:g} s), rtf {'max' if args.rtf == 0 else f'{args.rtf:g}'}"
        + ("" if bridge is None else f", ROS 2 namespaces {bridge.describe()}")
        + ("" if manager is None else f", controllers {', '.join(manager.controllers) or 'none'}"),
        file=sys.stderr,
        flush=True,
    )
    try:
        with StatusLine(loop, sim.nworld, backend, quiet=args.quiet) as status:
            stats = loop.run(status.report)
    finally:
        if bridge is not None:
            bridge.close()
        sim.shutdown()
    print(
        f"batchsim: stopped at sim time {loop.sim_time:.3f} s; last: {format_stats(stats, sim.nworld, backend)}",
        file=sys.stderr,
        flush=True,
    )
    return 0


#: the errors a command line, a file or the machine causes (each one line naming its cause)
USER_ERRORS = (
    UsageError, ModelError, ConfigurationError, BackendUnavailable, LifecycleError, ParamsError, MemoryCheckError,
    OptionError, RateError, SensorConfigError, DeclarationError,
)  # fmt: skip


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv and argv[0] == "info":
            return info(argv[1:])
        return run(argv)
    except USER_ERRORS as e:  # what the user can fix, as one line; an internal bug keeps its traceback
        print(f"batchsim: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return 0
    except BrokenPipeError:  # `batchsim info arm | head`
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
