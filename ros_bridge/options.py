"""The bridge's options, typed: what `batchsim`'s ROS flags become, and what Python callers pass.

Each option a flag sets names its flag here, beside its default (`_flag`, the field's
metadata): batchsim.cli.args builds the flag with that default and the options from the
parsed flags, so a default is said once. No rclpy here. Errors (batchsim.loop.OptionError)
name the option as Python spells it (`publish_rate`); the command line names its flag
(`--publish-rate`).
"""

from __future__ import annotations

import dataclasses
import enum
import math
import os
from collections.abc import Callable
from typing import Any

from batchsim.basics import AnyCase, OptionError
from batchsim.loop.rates import RateError, whole_ratio
from ros_bridge.naming import DEFAULT_TEMPLATE

#: worlds up to which the bridge runs inside the physics process by default
INPROCESS_WORLDS = 64
#: worlds per worker the default aims at, on a host with cores to spare
WORLDS_PER_WORKER = 128


def _flag(flag: str, parse: Callable[[Any], Any] | None = None) -> dict[str, Any]:
    """A field's metadata: the `batchsim` flag that sets the option (a bool's flag is a switch:
    `--no-...` turns off an option that is on by default) and what makes the flag's value the
    option's (None: taken as it is)."""
    return {"flag": flag, "parse": parse}


class Reliability(AnyCase, enum.Enum):
    """QoS reliability of every topic (`--reliability`, the MJCF plugin's topic_reliability: any case)."""

    RELIABLE = "reliable"
    BEST_EFFORT = "best_effort"


class ControllerNodes(AnyCase, enum.Enum):
    """Whether every world's controllers and controller_manager are ROS nodes (`--controller-nodes`):
    ON, OFF, or AUTO: for fleets of up to CONTROLLER_NODES_UP_TO worlds, and always in the root
    namespace (where a ros2_control stack's tools look for them)."""

    AUTO = "auto"
    ON = "on"
    OFF = "off"

    def wanted(self, namespaces: list[str]) -> bool:
        if self is ControllerNodes.AUTO:
            return len(namespaces) <= CONTROLLER_NODES_UP_TO or "" in namespaces
        return self is ControllerNodes.ON


#: AUTO's line: each world adds a node per controller and one for its controller_manager, each
#: with its parameter services, to the ROS graph every process discovers (benchmarks/discovery.py)
CONTROLLER_NODES_UP_TO = 32


@dataclasses.dataclass(frozen=True)
class RecordOptions:
    """What a recording (ros_bridge/recording.py) writes, and where to from the start.

    Attributes:
      path: an MCAP file to record into from the first period; None: only when asked
        (the `/batchsim/record` service).
      topics: topic names as `batchsim` serves them (`joint_states`, `odom`, `/tf`, `/clock`, ...);
        None: the default set (every state topic published from the start, /tf, /tf_static,
        /clock, robot_description).
      worlds: the worlds (indices 0..nworld-1) recorded; None: all.
      inputs: also every period's physics inputs, the model and the worlds' starts, so that
        `batchsim resim` can re-run the recorded worlds (batchsim.resim); not in a fleet of groups.
      group: one group's share of a fleet of several groups (batchsim.fleet.groups), recorded into
        one file with the others' (ros_bridge/bridge.py's join_bridges): `topics` may name what only
        another group publishes (join_bridges refuses a name no group publishes), and `worlds` may
        be empty for the first group, whose recording leads the others' (it holds /clock).
    """

    path: str | None = dataclasses.field(default=None, metadata=_flag("--record"))
    topics: tuple[str, ...] | None = dataclasses.field(default=None, metadata=_flag("--record-topics"))
    worlds: tuple[int, ...] | None = dataclasses.field(default=None, metadata=_flag("--record-worlds"))
    group: bool = False
    inputs: bool = dataclasses.field(default=True, metadata=_flag("--no-record-inputs"))


@dataclasses.dataclass(frozen=True)
class ViewOptions:
    """Where the fleet's web view (ros_bridge/view_plan.py) is served: `host` (127.0.0.1: this
    machine only; 0.0.0.0: every interface) and `port` (the next free one if it is taken)."""

    host: str = dataclasses.field(default="127.0.0.1", metadata=_flag("--view-host"))
    port: int = dataclasses.field(default=8080, metadata=_flag("--view-port"))


@dataclasses.dataclass(frozen=True)
class BridgeOptions:
    """How the fleet is bridged to ROS 2.

    Attributes:
      namespace: per-world namespace template with `{i}` (the world's number, offset included).
      publish_rate: Hz for joint_states, typed messages and controllers' outputs; None: every
        control period. Must divide the control rate.
      sensor_rate: Hz for `sensors/<sensor>` topics; None: the publish rate.
      qos_depth, reliability: QoS of every topic; None: the MJCF's mujoco.ros2 keys, else 10, reliable.
      command_timeout: sim seconds without a command after which a commanded world goes safe; None: never.
      lockstep: each control period waits until every world's command (or controller input) arrived.
      lockstep_timeout: wall seconds a lockstep period waits before it goes on.
      workers: bridge worker processes; 0 runs the bridge in the physics process; None: chosen
        from the world count and the cores (`default_workers`).
      world_offset: the number of this process's first world (`world_{offset}` ...), for a
        fleet spread over several processes or hosts.
      clock: publish `/clock`; exactly one process of a fleet may.
      fleet_services: serve `/batchsim/{reset,pause,step,record}` (worker 0); in a fleet of several
        groups of worlds, only the first group's bridge does (its loop pauses, steps and resets them all).
      startup_check: wall seconds to watch the ROS graph at start for another process that
        already serves these namespaces or `/clock` (on another host: one on this host is
        found at once, ros_bridge/registry.py; with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
        there is no other host to watch for).
      all_topics: create every per-world topic at start, also those otherwise created when
        someone asks (sensors, actuator commands, controller_state): for tools that list
        topics before they subscribe, at the price of discovery time in large fleets.
      tf: publish tf, tf_static and robot_description (ros_bridge/worker/tf.py).
      controller_nodes: a ROS node per controller of every world, and one per controller_manager,
        with their parameters (ros_bridge/worker/controller_nodes.py); ControllerNodes.
      description: the user's robot description (`--ros2-control`, xacro arguments after
        the path): robot_description publishes it where it is a URDF.
      description_topic: the topic the description was read from (`--robot-description-topic`):
        its publisher (robot_state_publisher's) keeps it; batchsim publishes no second one there.
      ros_args: ROS arguments for every worker's node, as after `--ros-args` on a ROS
        executable's command line (`-p use_sim_time:=true`, `-r from:=to`, `--log-level warn`).
      record: what a recording writes (MCAP, ros_bridge/recording.py); None: no recording, not even on request.
      view: serve the fleet's web view (ros_bridge/view_plan.py) there; None: no view.
    """

    namespace: str = dataclasses.field(default=DEFAULT_TEMPLATE, metadata=_flag("--namespace"))
    publish_rate: float | None = dataclasses.field(default=None, metadata=_flag("--publish-rate"))
    sensor_rate: float | None = dataclasses.field(default=None, metadata=_flag("--sensor-rate"))
    qos_depth: int | None = dataclasses.field(default=None, metadata=_flag("--qos-depth"))
    reliability: Reliability | None = dataclasses.field(default=None, metadata=_flag("--reliability", Reliability))
    command_timeout: float | None = dataclasses.field(default=None, metadata=_flag("--command-timeout"))
    lockstep: bool = dataclasses.field(default=False, metadata=_flag("--lockstep"))
    lockstep_timeout: float = dataclasses.field(default=1.0, metadata=_flag("--lockstep-timeout"))
    workers: int | None = dataclasses.field(default=None, metadata=_flag("--bridge-workers"))
    world_offset: int = dataclasses.field(default=0, metadata=_flag("--world-offset"))
    clock: bool = dataclasses.field(default=True, metadata=_flag("--no-clock"))
    fleet_services: bool = True
    startup_check: float = 1.0
    all_topics: bool = dataclasses.field(default=False, metadata=_flag("--all-topics"))
    tf: bool = dataclasses.field(default=True, metadata=_flag("--no-tf"))
    controller_nodes: ControllerNodes = dataclasses.field(
        default=ControllerNodes.AUTO, metadata=_flag("--controller-nodes", ControllerNodes)
    )
    description: str | None = dataclasses.field(default=None, metadata=_flag("--ros2-control"))
    description_topic: str | None = dataclasses.field(default=None, metadata=_flag("--robot-description-topic"))
    ros_args: tuple[str, ...] = dataclasses.field(default=(), metadata=_flag("--ros-args", tuple))
    record: RecordOptions | None = dataclasses.field(default_factory=RecordOptions)  # its own fields' flags
    view: ViewOptions | None = None  # `--view`: ViewOptions from its fields' flags

    def check(self) -> None:
        """OptionError for a value no fleet can run with (rates are checked against the loop later)."""
        for option in ("publish_rate", "sensor_rate"):
            value = getattr(self, option)
            if value is not None and not (value > 0 and math.isfinite(value)):
                raise OptionError(option, f"must be > 0 Hz, got {value:g}")
        if self.qos_depth is not None and self.qos_depth < 1:
            raise OptionError("qos_depth", f"must be >= 1, got {self.qos_depth}")
        if self.command_timeout is not None and not self.command_timeout > 0:
            raise OptionError("command_timeout", f"must be > 0 seconds, got {self.command_timeout:g}")
        if not self.lockstep_timeout > 0:
            raise OptionError("lockstep_timeout", f"must be > 0 seconds, got {self.lockstep_timeout:g}")
        if self.workers is not None and self.workers < 0:
            raise OptionError("workers", f"must be >= 0 (0: in the physics process), got {self.workers}")
        if self.world_offset < 0:
            raise OptionError("world_offset", f"must be >= 0, got {self.world_offset}")

    def decimation(self, option: str, control_rate: float) -> int:
        """Control periods between two messages of `publish_rate` or `sensor_rate`."""
        rate = getattr(self, option)
        if option == "sensor_rate" and rate is None:
            rate = self.publish_rate
        if rate is None:
            return 1
        try:
            return whole_ratio(control_rate, rate)
        except RateError as e:
            raise OptionError(option, f"{rate:g} Hz must divide the control rate {control_rate:g} Hz ({e.hint})") from None


def default_workers(nworld: int, cores: int | None = None) -> int:
    """Bridge worker processes for `nworld` worlds: one on a machine of 2 cores (publishing
    on the other core keeps the physics in real time: 16 arms at 1 kHz held RTF 1.00 with
    one worker against 0.39 publishing in the physics process, benchmarks/RESULTS.md), none
    on one core or up to INPROCESS_WORLDS worlds; else one per WORLDS_PER_WORKER worlds, at
    most half the cores (the rest serve the physics and the fleet's own subscribers)."""
    cores = cores or os.cpu_count() or 1
    if cores == 2:
        return 1
    if nworld <= INPROCESS_WORLDS or cores < 2:
        return 0
    return max(1, min(cores // 2, -(-nworld // WORLDS_PER_WORKER)))
