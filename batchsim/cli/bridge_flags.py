"""The bridge's flags (ROS 2, recording, the web view), built from ros_bridge/options.py, which
declares each option's flag beside its default; and the options the parsed flags say."""

from __future__ import annotations

import argparse
import dataclasses
import functools

from ros_bridge.options import (  # no rclpy: the options and their flags
    CONTROLLER_NODES_UP_TO,
    INPROCESS_WORLDS,
    WORLDS_PER_WORKER,
    BridgeOptions,
    ControllerNodes,
    RecordOptions,
    Reliability,
    ViewOptions,
)


def add_bridge_flags(p: argparse.ArgumentParser) -> None:
    """The groups of `batchsim`'s bridge flags: ROS 2 bridge, recording, the web view."""
    ros = p.add_argument_group("ROS 2 bridge")
    bridge = functools.partial(add_option, ros, BridgeOptions)
    bridge("namespace", help="per-world namespace template (default %(default)s)")
    bridge("publish_rate", type=float, help="Hz for topics (default: the control rate)")
    bridge("sensor_rate", type=float, help="Hz for sensors/<sensor> topics (default: the publish rate)")
    bridge("lockstep", help="each period waits for every world's command")
    bridge("lockstep_timeout", type=float, help="seconds a lockstep period waits")
    bridge("qos_depth", type=int, help="queue depth (default 10, or the MJCF's)")
    bridge("reliability", choices=tuple(r.value for r in Reliability))
    bridge("command_timeout", type=float, help="seconds without commands before a world goes safe")
    bridge(
        "workers",
        type=int,
        help=f"processes serving ROS (default: 1 on 2 cores; else 0 up to {INPROCESS_WORLDS} worlds, then one per "
        f"{WORLDS_PER_WORKER} worlds, at most half the cores); 0: in the physics process",
    )
    bridge("world_offset", type=int, help="number of the first world, for a fleet over several processes or hosts")
    bridge("clock", help="do not publish /clock (another process of the fleet does)")
    bridge(
        "all_topics",
        help="create every per-world topic at start (default: sensor, actuator and controller_state topics "
        "appear when someone subscribes or publishes)",
    )
    bridge("tf", help="publish no tf, tf_static or robot_description (default: every world's)")
    bridge(
        "controller_nodes",
        choices=tuple(c.value for c in ControllerNodes),
        help=f"a ROS node per controller and controller_manager of every world, with its parameters (default auto: "
        f"up to {CONTROLLER_NODES_UP_TO} worlds, and in the root namespace)",
    )
    rec = p.add_argument_group("recording (MCAP, as rosbag2 writes it)")
    add_option(rec, RecordOptions, "path", metavar="FILE", help="record every world's state topics into this MCAP file")
    add_option(
        rec,
        RecordOptions,
        "topics",
        type=_names,
        metavar="T,U,...",
        help="the topics recorded (default: joint_states and the other state topics published from the start, "
        "/tf, /tf_static, /clock, robot_description; a camera's or lidar's topics, e.g. front_camera/image_raw "
        "or scan, only when named)",
    )
    add_option(rec, RecordOptions, "worlds", type=world_list, metavar="I,J-K,...", help="the worlds recorded (default: all)")
    add_option(rec, RecordOptions, "inputs", help="record no physics inputs (they let `batchsim resim` re-run a recorded world)")
    view = p.add_argument_group("the web view")
    view.add_argument("--view", action="store_true", help="serve a web page showing every world in 3D, live")
    add_view_flags(view)


def add_view_flags(p: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """Where the web view is served (`batchsim --view`, `batchsim view`)."""
    add_option(p, ViewOptions, "host", help="the view's address (default %(default)s; 0.0.0.0: every interface)")
    add_option(p, ViewOptions, "port", type=int, help="the view's port (default %(default)s; the next free one if taken)")


def add_option(p: argparse.ArgumentParser | argparse._ArgumentGroup, options: type, name: str, **kwargs) -> None:
    """The flag of option `name` of `options` (ros_bridge.options declares it), with the option's
    default; a bool option's flag is a switch (`--no-...` for one that is on by default)."""
    field = _fields(options)[name]
    flag = field.metadata["flag"]
    if isinstance(field.default, bool):
        assert field.default == flag.startswith("--no-"), f"{flag} must turn {name} away from its default"
        p.add_argument(flag, action="store_true", **kwargs)
    else:
        p.add_argument(flag, default=field.default, **kwargs)


def _fields(options: type) -> dict[str, dataclasses.Field]:
    return {f.name: f for f in dataclasses.fields(options)}


def _dest(flag: str) -> str:
    """The attribute argparse keeps a flag's value in."""
    return flag.lstrip("-").replace("-", "_")


def _from_flags(options: type, args: argparse.Namespace) -> dict:
    """The options of class `options` that flags set, from the parsed flags."""
    out = {}
    for field in dataclasses.fields(options):
        flag = field.metadata.get("flag")
        if flag is None:
            continue
        value = getattr(args, _dest(flag))
        if isinstance(field.default, bool) and flag.startswith("--no-"):
            value = not value
        parse = field.metadata["parse"]
        out[field.name] = value if parse is None or value is None else parse(value)
    return out


def bridge_options(args: argparse.Namespace) -> BridgeOptions:
    """The bridge's options the parsed flags say (a recording's and the view's among them)."""
    return BridgeOptions(
        **_from_flags(BridgeOptions, args),
        record=RecordOptions(**_from_flags(RecordOptions, args)),
        view=ViewOptions(**_from_flags(ViewOptions, args)) if args.view else None,
    )


def option_flag(option: str) -> str:
    """The flag of an option an OptionError names (`workers` -> --bridge-workers; one the bridge's
    options do not declare is its name, dashed: `control_rate` -> --control-rate)."""
    field = _fields(BridgeOptions).get(option)
    flag = field.metadata.get("flag") if field is not None else None
    return flag or "--" + option.replace("_", "-")


def _names(text: str) -> tuple[str, ...]:
    """`joint_states,/tf` -> ("joint_states", "/tf")."""
    return tuple(t.strip() for t in text.split(",") if t.strip())


def world_list(text: str) -> tuple[int, ...]:
    """`0,3,8-11` -> (0, 3, 8, 9, 10, 11); argparse names the flag when this raises."""
    out: list[int] = []
    try:
        for part in (p.strip() for p in text.split(",") if p.strip()):
            lo, _, hi = part.partition("-")
            out += range(int(lo), int(hi) + 1) if hi else [int(lo)]
    except ValueError:
        raise argparse.ArgumentTypeError(f"worlds are indices or ranges I-J separated by commas, got {text!r}") from None
    return tuple(out)
