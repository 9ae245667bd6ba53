"""The command line's flags: the two parsers, every value checked before anything starts, and
the model the flags name (a --ros2-control file's `mujoco_model`, a URDF)."""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
import platform
import socket
import sys
import tomllib
from collections.abc import Callable, Sequence
from pathlib import Path

import batchsim
from batchsim.cli.bridge_flags import add_bridge_flags, add_option, add_view_flags, world_list
from batchsim.loop.realtime import DEFAULT_THREAD_PRIORITY
from ros_bridge.options import BridgeOptions  # no rclpy: the options and their flags

# The parsers import nothing heavy (MuJoCo, the models, the backends): `--help`, `--version` and a
# mistyped flag answer at once (issue 46). What checks the parsed arguments imports them then.

EXIT_USAGE = 2


class UsageError(Exception):
    """A problem the user can fix; printed as one line, exit code 2."""


class Parser(argparse.ArgumentParser):
    """An argparse parser whose errors are one line (UsageError, exit 2), not a usage dump."""

    def error(self, message: str) -> None:  # one line, exit 2, no usage dump
        raise UsageError(message)


def run_parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="batchsim",
        description="Run N copies of one MuJoCo robot, each on its own ROS 2 namespace.",
        epilog=(
            "commands: `batchsim info MODEL` lists a model's interfaces and sensors; `batchsim replay FILE` "
            "republishes an MCAP recording over ROS 2; `batchsim view FILE` shows one in the web view; "
            "`batchsim evaluate --controllers FILE` scores a policy controller over randomized worlds; "
            "`batchsim resim FILE --worlds I` re-runs recorded worlds' physics and compares; "
            "`batchsim calibrate REAL.mcap --randomize FILE` fits the model to a real robot's bag (each: --help). "
            "`--ros-args ... [--]` passes ROS arguments to every bridge worker's node (remaps, -p, --log-level)."
        ),
    )
    p.add_argument("--worlds", type=int, default=None, help=f"number of worlds (default {DEFAULT_WORLDS}; a fleet of groups: each group's, from its file)")
    p.add_argument(
        "--model",
        default=None,
        help="shipped model name or MJCF path (default: the --ros2-control file's mujoco_model param, else arm)",
    )
    p.add_argument(
        "--fleet",
        default=None,
        metavar="FILE",
        help="a fleet file (YAML): an environment and several robots in every world, each its own namespace",
    )
    concrete = ", ".join(b for b in backend_names() if b != "auto")  # registered ones too
    p.add_argument("--backend", default="auto", help=f"{concrete} or auto (default auto: picked for the hardware)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many simulated seconds")
    p.add_argument("--rtf", type=float, default=1.0, help="real-time factor; 0 runs as fast as possible")
    p.add_argument("--control-rate", type=float, default=None, help="Hz: commands applied, state read")
    p.add_argument("--threads", type=int, default=None, help="cpu backend: worker threads (default: all cores)")
    p.add_argument(
        "--thread-priority",
        type=int,
        default=DEFAULT_THREAD_PRIORITY,
        metavar="N",
        help=f"the loop thread's SCHED_FIFO priority while it paces --rtf, as controller_manager's thread_priority "
        f"(default {DEFAULT_THREAD_PRIORITY}; 0: the normal policy)",
    )
    p.add_argument(
        "--cpu-affinity",
        type=_cores,
        default=(),
        metavar="I,J,...",
        help="pin the loop thread to these cores, as controller_manager's cpu_affinity (default: any)",
    )
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
    add_option(p, BridgeOptions, "description", help="URDF/XML file with a <ros2_control> block")
    p.add_argument(
        "--robot-description-topic",
        default=None,
        metavar="TOPIC",
        help="take the robot description (URDF, as --ros2-control) from this topic, as robot_state_publisher latches it",
    )
    p.add_argument(
        "--robot-description-timeout", type=float, default=30.0, help="seconds to wait for it (default 30)"
    )
    _urdf_flags(p)
    p.add_argument(
        "--keyframe", default=None, help="keyframe (name or index) to start in (default: home, if the model has one)"
    )
    p.add_argument("--no-ros", action="store_true", help="run without the ROS 2 bridge")
    p.add_argument("--quiet", action="store_true", help="no live status line")
    p.add_argument(
        "--status-every",
        type=float,
        default=None,
        metavar="SECONDS",
        help="status line period (default: 1 s on a terminal, 10 s when stderr is a file or pipe)",
    )
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
    p.add_argument("--version", action=_Version, nargs=0, help="print the versions and exit")
    add_bridge_flags(p)  # ROS 2 bridge, recording, the web view
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
        "--randomize",
        default=None,
        metavar="FILE",
        help="per-world variation of model fields and the start pose (a `randomize:` YAML block); "
        "world i's draw depends on the seed and i (--world-offset included)",
    )
    p.add_argument(
        "--controllers",
        default=None,
        type=_controllers,
        help="ros2_control controller_manager YAML; none: no controllers; default: the shipped model's own "
        "(a fleet: each robot's, from its file)",
    )
    return p


def _controllers(text: str) -> str | None:
    """--controllers: a file, `none`, or `default` (as if not given: it overrides an earlier one)."""
    return None if text.lower() == "default" else text


def backend_names() -> list[str]:
    """batchsim.backends.names(), without importing the backends (MuJoCo) where nothing did yet:
    then no backend was registered, and the names are the shipped ones."""
    loaded = sys.modules.get("batchsim.backends")
    return loaded.names() if loaded is not None else list(SHIPPED_BACKENDS)


#: batchsim.backends.Backend's values (tests/test_cli.py checks they agree)
SHIPPED_BACKENDS = ("auto", "cpu", "mjx", "warp")


class _Version(argparse.Action):
    """--version, its line made when asked for (reading the packages' metadata costs the other
    answers a tenth of a second)."""

    def __call__(self, parser: argparse.ArgumentParser, *args: object) -> None:
        print(version_line())
        parser.exit()


def version_line() -> str:
    """`batchsim --version`: batchsim's and the engines' versions (from the distributions' metadata:
    importing MuJoCo to ask it would cost the answer a second)."""
    import importlib.metadata

    try:
        mujoco_version = importlib.metadata.version("mujoco")
    except importlib.metadata.PackageNotFoundError:
        mujoco_version = "not installed"
    return f"batchsim {batchsim_version()} (mujoco {mujoco_version}, python {platform.python_version()})"


def batchsim_version(installed_version: Callable[[str], str] | None = None) -> str:
    """The installed distribution's version (`installed_version`: importlib.metadata.version); for a
    source checkout on PYTHONPATH (no distribution metadata), the checkout's pyproject.toml's, marked as such."""
    import importlib.metadata

    try:
        return (installed_version or importlib.metadata.version)("batchsim")
    except importlib.metadata.PackageNotFoundError:
        pass
    pyproject = Path(batchsim.__file__).resolve().parents[1] / "pyproject.toml"
    try:
        project = tomllib.loads(pyproject.read_text())["project"]
    except (OSError, tomllib.TOMLDecodeError, KeyError):
        return "unknown (not installed)"
    if project.get("name") != "batchsim" or "version" not in project:
        return "unknown (not installed)"
    return f"{project['version']} (source checkout)"


def info_parser() -> argparse.ArgumentParser:
    p = Parser(prog="batchsim info", description="List a model's interfaces and sensors.")
    p.add_argument("model", nargs="?", help="shipped model name or MJCF path (default: as batchsim's --model)")
    p.add_argument("--fleet", default=None, metavar="FILE", help="a fleet file: each robot's interfaces, sensors and controllers")
    p.add_argument("--worlds", type=int, default=None, help=f"world count the backend choice is for (default {DEFAULT_WORLDS})")
    p.add_argument("--backend", default="auto")
    p.add_argument("--ros2-control", default=None)
    p.add_argument("--keyframe", default=None)
    _urdf_flags(p)
    p.add_argument("--mjcf", action="store_true", help="print the MJCF batchsim compiles (for a URDF: the one it generates)")
    p.add_argument("--sensors", action="append", metavar="FILE", help="as batchsim's --sensors: what it makes of them")
    p.add_argument("--randomize", default=None, metavar="FILE", help="as batchsim's --randomize: the distributions, and the draws of the first worlds")
    p.add_argument("--world-offset", type=int, default=0, help="with --randomize: the number of the first world shown")
    return p


def replay_parser() -> argparse.ArgumentParser:
    p = Parser(prog="batchsim replay", description="Republish an MCAP recording over ROS 2, with /clock.")
    p.add_argument("file", help="an MCAP file (batchsim --record, or any ROS 2 MCAP bag)")
    p.add_argument(
        "--worlds", type=world_list, default=None, metavar="I,J-K,...", help="the worlds replayed (default: all)"
    )
    p.add_argument("--rate", type=float, default=1.0, help="playback rate: 1 real time (default), 2 twice as fast")
    p.add_argument(
        "--delay", type=float, default=1.0, help="seconds between creating the publishers and the first message (discovery)"
    )
    return p


def view_parser() -> argparse.ArgumentParser:
    p = Parser(prog="batchsim view", description="Show an MCAP recording in the web view, scrubbed through.")
    p.add_argument("file", help="an MCAP file written by batchsim --record")
    add_view_flags(p)
    return p


def _urdf_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--mujoco-inputs", default=None, metavar="FILE",
        help="URDF model: a <mujoco_inputs> file (actuators, sensors, cameras, lidars), as mujoco_ros2_control's --m",
    )  # fmt: skip
    p.add_argument("--scene", default=None, metavar="FILE", help="URDF model: an MJCF scene file to add (lights, floor)")


DEFAULT_WORLDS = 16

def evaluate_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="batchsim evaluate",
        description="Run a policy controller over N randomized worlds for E episodes, commands drawn per world "
        "(seeded), and report success, tracking error and the worst worlds.",
    )
    p.add_argument("--model", default="arm", help="a shipped model's name or an MJCF file (default: arm)")
    p.add_argument("--controllers", required=True, help="the controller_manager YAML declaring the batchsim/PolicyController")
    p.add_argument("--controller", default=None, help="the policy controller's name, where the YAML declares several")
    p.add_argument("--randomize", default=None, help="the randomization YAML each world draws its conditions from")
    p.add_argument("--worlds", type=int, default=64)
    p.add_argument(
        "--world-offset", type=int, default=0, help="the first world's number: --worlds 1 --world-offset W reproduces world W"
    )
    p.add_argument("--episodes", type=int, default=3)
    p.add_argument("--episode-seconds", type=float, default=3.0)
    p.add_argument("--tolerance", type=float, default=0.1, help="success: the error below this at an episode's end (rad, m, m/s)")
    p.add_argument("--fall-height", type=float, default=None, help="a floating base below this height (m) has fallen")
    p.add_argument("--seed", type=int, default=0, help="the commands' seed (the conditions' is the randomize file's)")
    p.add_argument("--backend", default="cpu")
    p.add_argument("--worst", type=int, default=5, help="how many of the worst worlds to list")
    p.add_argument("--json", type=Path, default=None, help="write every world's results here")
    p.add_argument("--plot", type=Path, default=None, help="write a plot here (.png, .svg, .pdf)")
    return p


#: flags that describe one robot: a fleet file says them per robot
_ROBOT_FLAGS = ("model", "ros2_control", "keyframe", "mujoco_inputs", "scene")


def _load(args: argparse.Namespace) -> batchsim.RobotSpec:
    if getattr(args, "fleet", None) is not None:
        return batchsim.load_fleet(args.fleet)
    return batchsim.load(
        args.model, ros2_control=args.ros2_control, keyframe=args.keyframe, mujoco_inputs=args.mujoco_inputs, scene=args.scene
    )


_POSITIVE = {  # flag: what its number is, for the message; each must be finite and > 0
    "robot_description_timeout": "a finite number of seconds",
    "status_every": "a finite number of seconds",
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


def _cores(text: str) -> tuple[int, ...]:
    """`0,2,3` -> (0, 2, 3); argparse names the flag when this raises."""
    try:
        return tuple(int(c) for c in text.split(",") if c.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"cores are whole numbers separated by commas, got {text!r}") from None


def check_args(args: argparse.Namespace) -> None:
    """Every flag value the run will use, checked before anything starts.

    Raises:
      UsageError: the first bad value, as one line naming the flag and the value.
    """
    from batchsim import startup
    from batchsim.model import model_names

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
    check_fleet_args(args)
    take_urdf_model(args)
    args.model = default_model(args.model, args.ros2_control) if args.fleet is None else args.fleet
    model = Path(args.model).expanduser()
    if str(args.model) not in model_names() and model.is_dir():
        raise UsageError(f"--model {args.model}: is a directory, not an MJCF file")
    if args.log_dir is not None:
        try:
            batchsim.set_log_dir(args.log_dir)
        except ValueError as e:
            raise UsageError(f"--log-dir: {e}") from None
    if args.view and args.no_ros:
        raise UsageError("--view: the view reads the bridge's shared memory; it needs ROS (drop --no-ros)")
    if args.view and importlib.util.find_spec("viser") is None:
        raise UsageError(f"--view needs viser: {startup.install_command('view')}")
    if not 0 < args.view_port < 65536:
        raise UsageError(f"--view-port must be in 1..65535, got {args.view_port}")
    if args.view:
        try:  # viser would try port after port on an address it can never bind
            with socket.create_server((args.view_host, 0)):
                pass
        except OSError as e:
            raise UsageError(f"--view-host {args.view_host}: cannot serve there ({e.strerror or e})") from None
    recording = args.record is not None or args.record_topics is not None or args.record_worlds is not None
    if recording and args.no_ros:
        raise UsageError("--record: a recording is the bridge's topics; it needs ROS (drop --no-ros)")
    if args.record is not None:
        from ros_bridge.recording import path_problem  # no rclpy

        problem = path_problem(args.record)
        if problem is not None:
            raise UsageError(f"--record {problem}")
        if importlib.util.find_spec("mcap") is None or importlib.util.find_spec("mcap_ros2") is None:
            raise UsageError(f"--record needs the mcap packages: {startup.install_command('record')}")
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


def check_fleet_args(args: argparse.Namespace) -> None:
    """--fleet names every robot's model, description, keyframe and controllers in its file:
    the flags that say them for one robot are refused beside it, naming the file's key."""
    from batchsim.fleet.groups import has_groups, read_groups

    args.groups = None
    if args.fleet is None:
        if getattr(args, "worlds", 0) is None:
            args.worlds = DEFAULT_WORLDS
        return
    for flag in _ROBOT_FLAGS:
        if getattr(args, flag, None) is not None:
            dashed = "--" + flag.replace("_", "-")
            raise UsageError(f"{dashed}: a fleet names each robot's in its file (robots[k].{flag}); drop {dashed} or --fleet")
    controllers = getattr(args, "controllers", None)
    if controllers is not None and controllers.lower() != "none":
        raise UsageError(
            "--controllers: a fleet names each robot's in its file (robots[k].controllers); "
            "--controllers none runs none"
        )
    if not Path(args.fleet).expanduser().is_file():
        raise UsageError(f"--fleet {args.fleet}: no such file")
    if has_groups(args.fleet):  # several groups of worlds, each its own fleet file's (batchsim.fleet.groups)
        if getattr(args, "worlds", None) is not None:
            raise UsageError("--worlds: a fleet of groups gives each group's worlds in its file (groups[k].worlds); drop --worlds")
        args.groups = read_groups(args.fleet)
        args.worlds = args.groups.nworld
    elif getattr(args, "worlds", 0) is None:
        args.worlds = DEFAULT_WORLDS


def split_ros_args(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """(batchsim's arguments, the ROS arguments): what follows `--ros-args` up to a `--` (or the
    end), as every ROS executable takes it (rclpy.utilities.remove_ros_args), possibly
    several times. The ROS arguments go to every bridge worker's node."""
    ours: list[str] = []
    ros: list[str] = []
    inside = False
    for arg in argv:
        if arg == "--ros-args":
            inside = True
        elif arg == "--" and inside:
            inside = False
        else:
            (ros if inside else ours).append(arg)
    return ours, ros


def take_urdf_model(args: argparse.Namespace) -> None:
    """A URDF given as the model whose ros2_control block names its simulation (`mujoco_model`)
    is read as mujoco_ros2_control reads it: as the --ros2-control file, simulating that MJCF
    (so `batchsim info robot.urdf` shows the model `batchsim --ros2-control robot.urdf` runs),
    unless --mujoco-inputs or --scene are given to compile the URDF with."""
    from batchsim.model.description import model_file, read_description
    from batchsim.model.from_urdf import is_urdf

    model = getattr(args, "model", None)
    if model is None or args.ros2_control is not None or not is_urdf(model):
        return
    if getattr(args, "mujoco_inputs", None) is not None or getattr(args, "scene", None) is not None:
        return  # inputs or a scene to compile the URDF with: the URDF is the model
    try:
        names = model_file(read_description(model))
    except (OSError, ValueError):
        return  # the model's own load names what is wrong with the file
    if names is not None:
        args.ros2_control, args.model = model, None


def default_model(model: str | None, ros2_control: str | None) -> str:
    """`--model`, else the --ros2-control file's `mujoco_model` param (as mujoco_ros2_control
    finds its simulation), else that file itself if it is a URDF (compiled to MJCF, as
    mujoco_ros2_control does without one), else the shipped arm."""
    from batchsim.model.description import model_file, read_description
    from batchsim.model.from_urdf import is_urdf

    if model is not None:
        return model
    if ros2_control is not None:
        found = model_file(read_description(ros2_control))
        if found is not None:
            return found
        if is_urdf(ros2_control):
            return ros2_control
    return "arm"
