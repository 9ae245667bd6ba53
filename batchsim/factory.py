"""`batchsim.make` and `batchsim.make_groups`: a system of N worlds of a model on a backend,
and a fleet's groups of them (exported lazily by batchsim/__init__.py)."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from batchsim import backends
from batchsim.backends import Backend, backend_class, resolve
from batchsim.backends.sharded import ShardedSystem
from batchsim.contract import Contract
from batchsim.engine import Engine
from batchsim.fleet import is_fleet_file, load_fleet
from batchsim.fleet.groups import FleetGroups, Group, read_groups
from batchsim.hardware import BatchedSystem
from batchsim.model import RobotSpec, load
from batchsim.sensors import SensorConfig
from batchsim.types import OptionError
from batchsim.variation import Variation


def make(
    model: str | Path | RobotSpec | Mapping[str, Any],
    nworld: int = 1,
    backend: str | Backend | backends.Registered = "auto",
    *,
    ros2_control: str | Path | None = None,
    devices: Sequence[int | str] | str | None = None,
    processes: bool = False,
    sensors: SensorConfig | str | Path | Mapping[str, Any] | None = None,
    keyframe: str | int | None = None,
    randomize: Variation | str | Path | Mapping[str, Any] | None = None,
    world_offset: int = 0,
    **options: Any,
) -> Contract:
    """Build `nworld` worlds of `model` on `backend`, initialized (UNCONFIGURED).

    Args:
      model: a shipped model's name ("arm", "car", "quadruped"), a path to an MJCF file,
        a RobotSpec from `batchsim.load`, or a fleet: a fleet file (`.yaml`) or its mapping
        (`{"robots": [...]}`), several robots in every world (batchsim.fleet), each
        robot's interfaces prefixed `<robot>/` and listed in `sim.spec.robots`.
      nworld: number of worlds.
      backend: "cpu", "mjx", "warp", or "auto" (picks one for nworld and the hardware), or a
        name given to `batchsim.backends.register`.
      ros2_control: a robot description whose ros2_control blocks narrow the interfaces: a
        URDF/xacro/XML file path (xacro arguments may follow: "robot.urdf.xacro use_pid:=true")
        or XML text.
      keyframe: the keyframe (name or index) every world starts in and `reset` returns to;
        None: the block's `initial_keyframe`, else `home` when the model has one, else qpos0.
      devices: spread the worlds over several devices of a GPU backend (mjx, warp): "all",
        or a list of device indices (0, 1: the backend's GPUs in order) or names ("cuda:1",
        "cpu"). The worlds are split into contiguous ranges, one per device, behind the one
        contract (batchsim/backends/sharded/system.py). None: one device (the `device` option).
      processes: with several devices, run each device's share in a process of its own
        (the fleet's arrays in shared memory): the shards' host work then runs on several
        cores, which is what scales on several GPUs, but their device arrays stay in those
        processes (`device_arrays()` and `render(device=True)` give host copies). False: one
        thread per device in this process.
      sensors: cameras, lidars and sensor noise (batchsim.sensors.config): a SensorConfig, a
        YAML file (mujoco_ros2_control's plugin parameters and/or batchsim's `sensors:`
        block) or its parsed mapping. None: the model's cameras and lidars, no noise.
      randomize: per-world variation of model fields and the start pose (batchsim.variation):
        a Variation, a YAML file (its `randomize:` block) or its mapping; None: every world alike.
      world_offset: the number of world 0 in a larger fleet: world i draws as world
        `world_offset + i` (so `nworld=1, world_offset=731` reproduces world 731's draw).
      **options: backend options: `nthread` for "cpu"; `nconmax`, `njmax`, `max_data_bytes`,
        `device`, `graph` for "warp"; `device` for "mjx"; `deterministic` for every backend (bitwise-repeatable
        runs: always so on cpu, slower on a GPU). With "auto", those the chosen backend does
        not take are ignored, and `sim.reason` says so.

    Returns:
      The system, in UNCONFIGURED; call configure() and activate() to run it: a BatchedSystem
      owning the backend's engine, or with several devices a ShardedSystem over one each.
    """
    if isinstance(model, RobotSpec):
        if ros2_control is not None or keyframe is not None:
            raise ValueError("a RobotSpec is already loaded: give ros2_control= and keyframe= to batchsim.load")
        spec = model
    elif is_fleet_file(model):
        if ros2_control is not None or keyframe is not None:
            raise ValueError("a fleet names each robot's ros2_control and keyframe in its file, not make()")
        spec = load_fleet(model)
    else:
        spec = load(model, ros2_control=ros2_control, keyframe=keyframe)
    for warning in spec.warnings:  # what the description asks for and batchsim does not act on
        logging.getLogger("batchsim").warning("batchsim: warning: %s", warning)
    chosen, reason = resolve(backend, spec, nworld)
    cls = backend_class(chosen)
    if backends.parse(backend) is Backend.AUTO:
        # options meant for a backend auto did not pick (nconmax for warp) are dropped, and said so
        ignored = sorted(set(options) - set(cls.OPTIONS))
        options = {k: v for k, v in options.items() if k in cls.OPTIONS}
        if ignored:
            reason += f"; ignored {', '.join(ignored)}, which {chosen.value} does not take"
    if devices is not None:
        chosen_devices = _devices(cls, devices)
        if len(chosen_devices) > 1:
            sim = ShardedSystem(cls, build, spec, nworld, chosen_devices, processes=processes, **options)
            how = "a process each" if processes else "a thread each"
            sim.reason = f"{reason}; {len(chosen_devices)} devices, {how}: {', '.join(map(str, chosen_devices))}"
            sim.initialize()
            _configure_inputs(sim, sensors, randomize, world_offset)
            return sim
        options = {**options, "device": chosen_devices[0]}
    elif processes:
        raise OptionError("", "processes=True is for a fleet over several devices: give devices= too")
    sim = build(spec, nworld, cls, **options)
    sim.reason = reason
    sim.initialize()
    _configure_inputs(sim, sensors, randomize, world_offset)
    return sim


def make_groups(
    source: str | Path | Mapping[str, Any] | FleetGroups,
    backend: str | Backend | backends.Registered = "auto",
    *,
    world_offset: int = 0,
    **kwargs: Any,
) -> list[tuple[Group, Contract]]:
    """A fleet of several groups of worlds (batchsim.fleet.groups: a fleet file's `groups:`, each
    its own robots and world count): one system per group, each made as make() makes one (the
    same backend, sensors, randomization and options), its worlds numbered from the group's
    first world of the fleet (world_offset + the groups before it), UNCONFIGURED.

    Returns (group, system) pairs in the fleet's order. One loop steps them under one clock:
    `SimLoop(first)` and `.join(SimLoop(each other))` (batchsim.loop).
    """
    fleet = source if isinstance(source, FleetGroups) else read_groups(source)
    return [
        (g, make(load_fleet(g.fleet), g.worlds, backend, world_offset=world_offset + g.first_world, **kwargs))
        for g in fleet.groups
    ]


def build(spec: RobotSpec, nworld: int, engine: type[Engine], **options: Any) -> BatchedSystem:
    """`nworld` worlds of `spec` on a new `engine(spec, nworld, **options)`, the system not yet
    initialized (UNKNOWN): what make() builds on one device, and each device's shard of a fleet
    over several (batchsim.backends.sharded)."""
    return BatchedSystem(spec, nworld, engine(spec, nworld, **options))


def _configure_inputs(sim: Contract, sensors: Any, randomize: Any, world_offset: int) -> None:
    """What make() hands a new system before configure: its sensors and its per-world variation
    (with a fleet's robots placed at random per world, batchsim.fleet). A fleet's robots' own
    sensors files (`spec.sensor_config`) are applied, `sensors` laid over them (batchsim.fleet.sensors)."""
    if sim.spec.sensor_config is not None:
        from batchsim.fleet.sensors import merged

        sensors = merged(sim.spec, sensors)
    if sensors is not None:
        sim.set_sensor_config(sensors)
    if sim.spec.placements:
        import dataclasses

        from batchsim.variation import load as load_variation

        given = load_variation(randomize) if randomize is not None else Variation()
        randomize = dataclasses.replace(given, placements=given.placements + tuple(sim.spec.placements))
    if randomize is not None or world_offset:
        sim.set_variation(randomize, first_world=world_offset)


def _devices(cls: type[Engine], devices: Sequence[int | str] | str) -> list[Any]:
    """The `device` option of each shard: "all" is every device the backend has; an index
    picks from them; a name is the backend's own."""
    available = getattr(cls, "available_devices", None)
    if available is None:
        raise OptionError("", f"the {cls.name} backend runs on the host's cores: devices= is for mjx and warp")
    have = available()
    if isinstance(devices, str):
        if devices.lower() != "all":
            raise OptionError("", f"devices must be 'all' or a list of device indices or names, got {devices!r}")
        return list(have)
    chosen: list[Any] = []
    for d in devices:
        if isinstance(d, int | np.integer) and not isinstance(d, bool):
            if not 0 <= d < len(have):
                raise OptionError("", f"device {d} does not exist: the {cls.name} backend has {', '.join(have)}")
            chosen.append(have[int(d)])
        elif str(d) in have or str(d).partition(":")[0] == "cpu":  # the host's CPU is a device too
            chosen.append(d)
        else:
            raise OptionError("", f"device {d!r} does not exist: the {cls.name} backend has {', '.join(have)}")
    if not chosen:
        raise OptionError("", "devices is empty: name at least one device")
    return chosen
