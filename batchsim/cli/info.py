"""`batchsim info`: a model's interfaces, sensors, cameras, lidars and warnings, or its MJCF."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Any

import numpy as np

from batchsim.backends import resolve
from batchsim.cli.args import (
    UsageError,
    _load,
    check_fleet_args,
    default_model,
    info_parser,
    take_urdf_model,
)  # fmt: skip
from batchsim.fleet import load_fleet
from batchsim.model import CommandMode, RobotSpec
from batchsim.plugins.base_velocity import BaseVelocity
from batchsim.sensors import SensorConfig, SensorSuite
from batchsim.variation import Bound
from batchsim.variation import load as load_variation
from batchsim.variation.report import changes, describe


def info(argv: Sequence[str]) -> int:
    args = info_parser().parse_args(argv)
    if args.fleet is not None and args.model is not None:
        raise UsageError(f"batchsim info: give a model or --fleet, not both ({args.model!r} and --fleet {args.fleet})")
    check_fleet_args(args)
    take_urdf_model(args)
    args.model = default_model(args.model, args.ros2_control)
    sensors = SensorConfig.from_flags(args.sensors)
    if args.groups is not None:  # a fleet of several groups of worlds: each group's world, in turn
        if args.mjcf:
            raise UsageError("--mjcf: a fleet of groups has one world model per group: give a group's fleet file")
        out = [f"fleet      {args.groups.name}  ({args.groups.where}): {args.groups.nworld} worlds in {len(args.groups.groups)} groups"]
        for g in args.groups.groups:
            last = g.first_world + g.worlds - 1
            out.append(f"\n=== group {g.name}: worlds {g.first_world}..{last} ({g.worlds}), {g.fleet.where}")
            out += model_lines(args, load_fleet(g.fleet), g.worlds, sensors)
        print("\n".join(out))
        return 0
    spec = _load(args)
    if args.mjcf:
        print(spec.xml)
        return 0
    print("\n".join(model_lines(args, spec, args.worlds, sensors)))
    return 0


def model_lines(args: argparse.Namespace, spec: RobotSpec, nworld: int, sensors: SensorConfig | None) -> list[str]:
    """What `batchsim info` says of one world model in `nworld` worlds: its backend, start, robots,
    interfaces, sensors, plugins, randomization, warnings and problems."""
    chosen, reason = resolve(args.backend, spec, nworld)
    m = spec.mjmodel
    keys = ", ".join(repr(k) if k else f"#{i}" for i, k in enumerate(spec.keyframes)) or "none"
    base = spec.floating_base
    out = [
        f"model      {spec.name}  ({spec.path or 'string'})",
        f"timestep   {m.opt.timestep:g} s   nq {m.nq}  nv {m.nv}  nu {m.nu}",
        f"backend    {chosen.value} for {nworld} worlds ({reason})",
        f"starts in  {spec.initial.source}   (keyframes: {keys})",
        f"base       {f'free joint {base.joint!r} of body {base.body!r}' if base else 'per robot (below)' if spec.robots else 'fixed (no floating base)'}",
    ]
    if spec.ros is not None:
        r = spec.ros
        out.append(
            f"mujoco.ros2 ros_namespace={r.ros_namespace!r} topic_queue_size={r.topic_queue_size} "
            f"topic_reliability={r.topic_reliability}"
        )
    if spec.robots:
        out += robot_lines(spec, nworld)
    out.append(f"\nstate interfaces ({len(spec.state)})")
    out += [f"  {i:3d}  {c.name}" for i, c in enumerate(spec.state)]
    out.append(f"\ncommand interfaces ({len(spec.commands)})")
    out += [
        f"  {i:3d}  {c.name:32s} "
        + (f"transmission {c.actuator}" if c.mode is CommandMode.TRANSMITTED else f"actuator {c.actuator}{_how(c)}")
        for i, c in enumerate(spec.commands)
    ]
    out += [
        f"       {mc.joint} mimics {mc.source} (x {mc.multiplier:g} + {mc.offset:g}) on actuator {mc.actuator}"
        for mc in spec.mimics
    ]
    for t in spec.transmissions:
        out.append(f"       transmission {t.name}: {t.kind.value.rsplit('/', 1)[1]} {', '.join(t.joints)} -> "
                   f"{', '.join(t.actuators)} (actuator position = {[list(r) for r in t.matrix]} x joint)")
        out += [f"         {c.name:30s} actuator {c.actuator}{_how(c)}"
                for c in spec.actuator_commands or () if c.name.rsplit("/", 1)[0] in t.actuators]
    out.append(f"\nsensors ({len(spec.sensors)})")
    out += [
        f"  {s.name:24s} {s.type_name:14s} dim {s.dim}  ({', '.join(s.fields)})" for s in spec.sensors
    ]
    if spec.sensor_config is not None:  # a fleet's robots' own sensors files, --sensors laid over them
        from batchsim.fleet.sensors import merged

        sensors = merged(spec, sensors)
    suite = SensorSuite.build(spec, nworld, sensors)
    out += sensor_lines(suite)
    plugin = suite.config.base_velocity
    if plugin is not None:
        BaseVelocity(plugin, m, 1)  # its body checked: ConfigurationError names it
        kind = "TwistStamped" if plugin.use_stamped_twist else "Twist"
        out.append(
            f"\nbase velocity plugin {plugin.name}: body {plugin.body!r} held at <ns>/{plugin.cmd_vel_topic.lstrip('/')} "
            f"({kind}), at most {plugin.max_linear_velocity:g} m/s and {plugin.max_yaw_rate:g} rad/s, "
            f"stopped {plugin.cmd_timeout:g} s after the last"
        )
    wrench = suite.config.external_wrench
    if wrench is not None:
        out.append(
            f"\nexternal wrench plugin {wrench.name}: service <ns>/{wrench.service} "
            "(mujoco_ros2_control_msgs/ApplyExternalWrench), answered once the wrenches ran in sim time; "
            "no ~/wrench_markers"
        )
    if args.randomize is not None:
        out += randomization_lines(spec, args.randomize, args.world_offset, min(nworld, 4))
    warnings = spec.warnings + suite.config.warnings
    if warnings:
        out.append("\nwarnings (not acted on)")
        out += [f"  {w}" for w in warnings]
    if spec.problems:
        out.append("\nproblems (configure will fail)")
        out += [f"  {p}" for p in spec.problems]
    return out


def robot_lines(spec: RobotSpec, nworld: int) -> list[str]:
    """`batchsim info --fleet`: each robot, where it stands, its interfaces, sensors and controllers."""
    from batchsim.controllers.robots import load_fleet_controllers, robot_controllers_file

    manager = load_fleet_controllers(spec, nworld)
    out = [f"\nrobots ({len(spec.robots)})"]
    for r in spec.robots:
        x, y, z, yaw = r.pose
        base = r.floating_base
        source = robot_controllers_file(r)
        out.append(
            f"  {r.name}: {r.model} at ({x:g}, {y:g}, {z:g}) yaw {yaw:g} rad, "
            + (f"floating base {r.local(base.body)!r}" if base else "fixed base")
            + f"; {len(r.state)} state and {len(r.commands)} command interfaces, {len(r.sensors)} sensors"
        )
        out.append("    commands  " + (", ".join(spec.command_interfaces[c].removeprefix(r.prefix) for c in r.commands) or "none"))
        if r.sensors:
            out.append("    sensors   " + ", ".join(r.local(s) for s in r.sensors))
        names = [c.removeprefix(r.prefix) for c in (manager.controllers if manager else ()) if c.startswith(r.prefix)]
        out.append(f"    controllers ({source if source else 'none'}): {', '.join(names) or 'none'}")
    return out


def randomization_lines(spec: RobotSpec, source: str, first: int, count: int) -> list[str]:
    """`batchsim info --randomize`: the distributions, then what the first worlds draw."""
    variation = load_variation(source)
    bound = Bound(variation, spec.mjmodel)
    out = [f"\nrandomization ({source})"] + [f"  {line}" for line in describe(variation)]
    worlds = np.arange(first, first + count)
    params = bound.draw(worlds, np.zeros(count, np.int64))
    for row, world in enumerate(worlds):
        lines = changes(bound, spec.mjmodel, params, row)
        out.append(f"  world {world}:{'' if lines else ' as the model'}")
        out += [f"    {line}" for line in lines]
        qpos = bound.start_qpos(worlds[row : row + 1], np.zeros(1, np.int64), spec.initial.qpos)
        if qpos is not None:
            out.append(f"    start qpos {np.array2string(qpos[0], precision=4, max_line_width=200)}")
    return out


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
