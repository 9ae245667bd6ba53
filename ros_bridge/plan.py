"""What the bridge serves, as data: the plan every worker gets once, at start. No rclpy here.

The physics process builds a `FleetPlan` from the system, the options and the controllers'
declared topics (batchsim/controllers/topics.py): per-world outputs (topic, message type,
which columns of which channel fill which field), inputs (topic, kind, slot block), the
names, QoS and rates, and the shared-memory layout. Channels are (nworld, width) float64
arrays the physics process copies into shared memory at publish periods, when some
worker has a subscriber for an output that reads them.

Adding a message kind to the bridge (a sensor's Image, LaserScan, ...): give it a row in
ros_bridge/worker/messages.py's FIELD_PATHS (which message fields each named field fills) and
add an output here whose channel the physics process fills.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence

import numpy as np

from batchsim.contract import Contract
from batchsim.controllers import ControllerManager
from batchsim.controllers.topics import OUTPUT_FIELDS, ActionKind, Input, MessageKind, Output
from batchsim.controllers.trajectory import DEFAULT_MAX_POINTS
from batchsim.loop import OptionError
from batchsim.memory import Layout, ring_arrays
from batchsim.model import RobotSpec
from batchsim.plugins.base_velocity import HELD_DOFS, command_problem
from batchsim.types import split_worlds
from ros_bridge.action_plan import (
    ACTION_MONITOR_RATE,
    GripperActionSpec,
    TrajectoryActionSpec,
    gripper_action,
    trajectory_action,
)
from ros_bridge.input_recording import inputs_layout
from ros_bridge.interfaces import available
from ros_bridge.manager_link import ManagerSpec, manager_spec
from ros_bridge.naming import ros_names, world_namespaces, worlds_label
from ros_bridge.options import BridgeOptions, Reliability
from ros_bridge.outputs import ChannelFill, Field, OutputSpec, robot_outputs
from ros_bridge.protocol.active import active_arrays
from ros_bridge.protocol.commands import rejection_arrays, slot_arrays
from ros_bridge.protocol.demand import demand_arrays
from ros_bridge.protocol.goals import held_arrays, refusal_arrays
from ros_bridge.protocol.liveness import liveness_arrays
from ros_bridge.protocol.requests import trajectory_bytes, wrench_arrays
from ros_bridge.protocol.sensor_blocks import camera_request_arrays
from ros_bridge.protocol.services import service_arrays
from ros_bridge.protocol.snapshot import snapshot_arrays
from ros_bridge.protocol.world_params import param_arrays
from ros_bridge.recording import RecordSpec, record_spec
from ros_bridge.sensor_topics import SensorPlan, sensor_plan
from ros_bridge.tf_plan import TfSpec, tf_spec
from ros_bridge.view_plan import ViewSpec, view_spec

log = logging.getLogger("batchsim.ros_bridge")

#: outputs whose topic holds one of these parts are created only when a subscriber appears
ON_REQUEST_PARTS = ("/controller_state/",)
RING_BASE = 1 << 18  # bytes of each worker's ring, plus RING_PER_WORLD per world it serves
RING_PER_WORLD = 8 << 10


@dataclasses.dataclass(frozen=True)
class InputSpec:
    """Messages every world takes on `<ns>/<topic>`, for a controller.

    Attributes:
      topic: under the world's namespace.
      kind: the message kind.
      slots: the name of its slot block in shared memory (fixed-size kinds) and of its
        arrival counters (every kind).
      width: values per message of a fixed-size kind.
      joints: JOINT_TRAJECTORY: the controller's joints.
      max_points: JOINT_TRAJECTORY: more points are rejected (0: no limit).
      controller: the controller's name, for messages.
    """

    topic: str
    kind: MessageKind
    slots: str
    width: int = 0
    joints: tuple[str, ...] = ()
    max_points: int = 0
    controller: str = ""


@dataclasses.dataclass(frozen=True)
class ChannelSpec:
    name: str
    width: int


@dataclasses.dataclass
class FleetPlan:
    """Everything a worker needs, picklable. World indices are local (0 .. nworld-1); the
    world's number in names is `world_offset + index`.

    Attributes:
      nworld: worlds of this process.
      world_offset: the number of its first world.
      namespaces: (nworld,) without leading `/`.
      ranges: per worker, its worlds [lo, hi).
      node_names: per worker, its node's name.
      qos_depth, reliability: every topic's QoS.
      control_rate: Hz.
      interfaces: command interface names, in column order.
      actuator_topics: per column, the `actuators/<name>/command` token (the robot's own name of
        the actuator, in a world of several robots).
      actuator_robots: per column, the robot's prefix the topic is under (`<robot>/actuators/...`),
        "" for a world of one robot (given empty: all "").
      robots: the robots every world holds (a fleet file's), named in /diagnostics; empty for one.
      robot_commands: per robot, its command columns: its `<ns>/<robot>/commands` vector's order.
      owners: per column, the controller that claimed it, or "".
      channels, outputs, inputs: see above.
      lockstep: workers nudge the loop when a command arrives.
      clock: worker 0 publishes /clock.
      fleet_services: worker 0 serves /batchsim/{reset,pause,step,record}.
      startup_check: seconds worker 0 watches the graph for another fleet at start.
      all_topics: create the on-request topics at start too.
      controller_nodes: a node per controller and controller_manager of every world (BridgeOptions).
      sensors: cameras and lidars (ros_bridge/sensor_topics.py), or None.
      tf: the tf tree and robot description, or None.
      manager: the controller_manager services' data, or None without controllers.
      actions: the FollowJointTrajectory and GripperCommand actions (ros_bridge/action_plan.py).
      wrench_service: the ExternalWrenchPlugin's service under each world's namespace
        (`external_wrench/apply_wrench`, batchsim.plugins.external_wrench), or "" without the plugin.
      recording: what a recording writes (ros_bridge/recording.py), or None without recording.
      view: what the web view draws and where it serves (ros_bridge/view_plan.py), or None.
      layout, memory_name: the shared arrays.
    """

    nworld: int
    world_offset: int
    namespaces: list[str]
    ranges: list[tuple[int, int]]
    node_names: list[str]
    qos_depth: int
    reliability: Reliability
    control_rate: float
    interfaces: list[str]
    actuator_topics: list[str]
    owners: list[str]
    channels: list[ChannelSpec]
    outputs: list[OutputSpec]
    inputs: list[InputSpec]
    lockstep: bool
    clock: bool
    startup_check: float
    all_topics: bool = False
    controller_nodes: bool = False
    fleet_services: bool = True
    actuator_robots: list[str] = dataclasses.field(default_factory=list)
    robots: tuple[str, ...] = ()  # a fleet file's robots in every world (batchsim.fleet), for /diagnostics
    robot_commands: tuple[tuple[int, ...], ...] = ()  # per robot, its command columns
    ros_args: tuple[str, ...] = ()  # after --ros-args, for every worker's rclpy.init
    sensors: SensorPlan | None = None
    tf: TfSpec | None = None
    manager: ManagerSpec | None = None
    actions: list[TrajectoryActionSpec | GripperActionSpec] = dataclasses.field(default_factory=list)
    wrench_service: str = ""
    recording: RecordSpec | None = None
    view: ViewSpec | None = None
    randomized: bool = False  # the worlds' draws (batchsim.variation) go into /diagnostics
    layout: Layout = dataclasses.field(init=False)
    memory_name: str | None = None

    def __post_init__(self) -> None:
        self.actuator_robots = self.actuator_robots or [""] * len(self.actuator_topics)
        n, ncmd, nw = self.nworld, len(self.interfaces), len(self.ranges)
        arrays: list[tuple[str, tuple[int, ...], str]] = [
            *snapshot_arrays(n, [ch.width for ch in self.channels]),  # protocol/snapshot.py
            *demand_arrays(nw, len(self.channels), self.view is not None),  # protocol/demand.py
            *service_arrays(nw),  # protocol/services.py
            *liveness_arrays(nw),  # protocol/liveness.py
        ]
        arrays += slot_arrays("cmd", n, ncmd, per_column=True)
        for spec in self.inputs:
            if spec.kind is MessageKind.JOINT_TRAJECTORY:
                arrays.append((f"{spec.slots}.seq", (n,), "i8"))
            else:
                arrays += slot_arrays(spec.slots, n, spec.width, per_column=False)
        arrays += rejection_arrays("rej", n) + rejection_arrays("hrej", n)
        if self.sensors is not None:
            arrays += self.sensors.arrays(n)
        if self.manager is not None:
            arrays += active_arrays(n, len(self.manager.controllers))  # protocol/active.py
        if self.actions:  # per world: the last goal the loop refused, and why
            arrays += refusal_arrays(n) + held_arrays(n, len(self.actions))  # protocol/goals.py
        if self.wrench_service:
            arrays += wrench_arrays(nw)
        if self.recording is not None:
            arrays += self.recording.arrays(len(self.channels))
        if self.view is not None and self.sensors is not None and self.sensors.cameras:
            arrays += camera_request_arrays()  # the camera image the view shows (protocol/sensor_blocks.py)
        if self.randomized:
            arrays += param_arrays(n)
        # room for two of the largest trajectories an input takes (a record may take at most
        # half the ring): a 10,000-point trajectory of 6 joints is 1.5 MB
        largest = max(
            (trajectory_bytes(spec.max_points or DEFAULT_MAX_POINTS, len(spec.joints))
             for spec in self.inputs if spec.kind is MessageKind.JOINT_TRAJECTORY),
            default=0,
        )  # fmt: skip
        for j, (lo, hi) in enumerate(self.ranges):
            arrays += ring_arrays(f"ring{j}", RING_BASE + RING_PER_WORLD * (hi - lo) + 2 * largest)
        self.layout = Layout(arrays)

    @property
    def nworker(self) -> int:
        return len(self.ranges)

    def world_name(self, index: int) -> str:
        return self.namespaces[index]


# The bridge's own per-world byte beside the contract's Status bits: the snapshot's and the
# recording ring's `flags` (protocol/snapshot.py, protocol/recording.py), which the workers,
# the recorder and the view read. Not Status bits under other names, and kept apart on
# purpose: FLAG_BAD is the bridge's rejection alone (Status.BAD_COMMAND is write()'s too),
# FLAG_TIMED_OUT has no Status bit, and FLAG_FROZEN is the host's one-bit summary of
# `status & batchsim.types.FROZEN`, made once per snapshot. Their values are the protocol's.
FLAG_BAD = 1  # the bridge rejected this world's last command
FLAG_TIMED_OUT = 2  # --command-timeout: the world went safe
FLAG_FROZEN = 4  # diverged or overflowed (status & FROZEN): frozen until reset



def _robot_prefix(spec: RobotSpec, name: str) -> str:
    """The prefix of the robot a world name belongs to (a fleet's world), else ""."""
    return next((r.prefix for r in spec.robots if name.startswith(r.prefix)), "")


def _actuator_tokens(spec: RobotSpec) -> list[str]:
    """Each command column's actuator as a ROS token, made distinct within its robot."""
    prefixes = [_robot_prefix(spec, c.actuator) for c in spec.commands]
    out = [""] * len(spec.commands)
    for prefix in dict.fromkeys(prefixes):
        cols = [c for c, p in enumerate(prefixes) if p == prefix]
        for c, token in zip(cols, ros_names([spec.commands[c].actuator.removeprefix(prefix) for c in cols]), strict=True):
            out[c] = token
    return out


def build_plan(
    sim: Contract,
    control_rate: float,
    options: BridgeOptions,
    manager: ControllerManager | None,
    nworker: int,
    extra_outputs: Sequence[Output] = (),
) -> tuple[FleetPlan, list[ChannelFill], list[Input]]:
    """The plan for `sim`, with, for the physics side, each channel's fill function
    (`fill(out (nworld, width))`, called in the loop thread) and each input's `apply`.

    `extra_outputs` are more per-world messages (a sensor's), served like a controller's."""
    options.check()
    spec = sim.spec
    nworld = sim.nworld
    plugin = spec.ros
    namespaces = world_namespaces(
        nworld, options.namespace, plugin.ros_namespace if plugin else None, offset=options.world_offset
    )
    depth = options.qos_depth if options.qos_depth is not None else (plugin.topic_queue_size if plugin else 10)
    reliability = options.reliability or Reliability(plugin.topic_reliability if plugin else "reliable")
    publish_every = options.decimation("publish_rate", control_rate)
    sensor_every = options.decimation("sensor_rate", control_rate)

    channels: list[ChannelSpec] = []
    fills: list[ChannelFill] = []
    outputs: list[OutputSpec] = []

    def channel(name: str, width: int, fill: ChannelFill) -> int:
        channels.append(ChannelSpec(name, width))
        fills.append(fill)
        return len(channels) - 1

    topics = [c.topics() for c in manager] if manager is not None else []
    owners = [""] * len(spec.commands)
    if manager is not None:
        for c, name in enumerate(spec.command_interfaces):
            owners[c] = manager.owner.get(name, "")

    # the robots (a world of one: "") whose joint_states a joint state broadcaster publishes
    replaced = {c.namespace for c, t in zip(manager, topics, strict=True) if t.replaces_joint_states} if manager else set()
    outputs += robot_outputs(sim, channel, publish_every, sensor_every, replaced=replaced)

    # the controllers' outputs and inputs
    inputs: list[Input] = []
    input_specs: list[InputSpec] = []
    for out in extra_outputs:
        outputs.append(_controller_output(out, nworld, publish_every, channel))
    for t in topics:
        for out in t.outputs:
            package = out.kind.value.partition("/")[0]
            if available().get(package, True):  # a message package batchsim builds, missing: no topic
                outputs.append(_controller_output(out, nworld, publish_every, channel))
        for inp in t.inputs:
            slots = f"in{len(inputs)}"
            width = 0 if inp.kind is MessageKind.JOINT_TRAJECTORY else inp.row_width()
            inputs.append(inp)
            input_specs.append(
                InputSpec(inp.topic, inp.kind, slots, width, tuple(inp.joints), inp.max_points, t.controller)
            )

    if sim.base_velocity is not None:  # mujoco_ros2_control's BaseVelocityPlugin: <ns>/cmd_vel
        inp = _base_velocity_input(sim)
        config = sim.base_velocity.config
        clash = next((s for s in input_specs if s.topic.strip("/") == inp.topic.strip("/")), None)
        if clash is not None:
            raise OptionError(
                "", f"{config.where}.cmd_vel_topic: {inp.topic} is {clash.controller}'s input too: give one another topic"
            )
        inputs.append(inp)
        input_specs.append(InputSpec(inp.topic, inp.kind, f"in{len(inputs) - 1}", inp.row_width(), controller=config.name))

    transforms = [tr for t in topics for tr in t.transforms]  # a diff drive's odom -> base_link
    tf = (
        tf_spec(sim, publish_every, channel, options.description, transforms, options.description_topic)
        if options.tf and available()["tf2_msgs"]
        else None
    )
    actions: list[TrajectoryActionSpec | GripperActionSpec] = []
    if manager is not None and available()["control_msgs"]:
        monitor_every = max(1, round(control_rate / ACTION_MONITOR_RATE))
        for k, (c, t) in enumerate(zip(manager, topics, strict=True)):
            if t.action is ActionKind.GRIPPER_COMMAND:
                actions.append(gripper_action(c, k, monitor_every, channel))
            elif t.action is ActionKind.FOLLOW_JOINT_TRAJECTORY:
                i = next(i for i, spec in enumerate(input_specs) if spec.controller == c.name and spec.joints)
                actions.append(trajectory_action(c, k, i, monitor_every, input_specs[i].max_points, channel))

    wrench = sim.sensors.config.external_wrench  # mujoco_ros2_control's ExternalWrenchPlugin
    ranges = [(r.start, r.stop) for r in split_worlds(nworld, max(1, min(nworker, nworld)))]
    offset = options.world_offset
    sensors = sensor_plan(sim)
    if tf is not None:  # a frame id a message names but no tree holds: RViz shows the message nowhere
        stamped = [(o.topic, f) for o in outputs for f in (o.frame_id, o.child_frame_id)]
        for topic, frame in tf.unknown_frames(stamped):
            log.warning(
                "batchsim: tf: %s is stamped with frame %r, which is in no world's tf tree (no body, site or "
                "camera of the model)", topic, frame.removeprefix("{ns}/"),
            )  # fmt: skip
    recording = None
    if options.record is not None:
        widths = [c.width for c in channels]
        tf_channel = tf.channel if tf else None
        recording = record_spec(options.record, outputs, widths, tf_channel, options.clock, nworld, sensors)
        if options.record.inputs and recording.worlds:  # what resim needs (batchsim.resim)
            recording = dataclasses.replace(recording, inputs=inputs_layout(sim))
    view = None
    if options.view is not None:
        if tf is None:
            raise OptionError("view", "draws the robots from tf's body poses: it needs tf (drop --no-tf)")
        js = next((o for o in outputs if o.topic == "joint_states"), None)
        position = next((f for f in js.fields if f.name == "position"), None) if js is not None else None
        joints = (position.channel, position.columns, js.names) if position is not None else None
        view = view_spec(sim, tf.channel, tf.bodies, options.view.host, options.view.port, joints)
    plan = FleetPlan(
        nworld=nworld,
        world_offset=offset,
        namespaces=namespaces,
        ranges=ranges,
        node_names=[f"batchsim_{offset + lo}_{offset + hi - 1}" for lo, hi in ranges],
        qos_depth=depth,
        reliability=reliability,
        control_rate=control_rate,
        interfaces=list(spec.command_interfaces),
        actuator_topics=_actuator_tokens(spec),
        actuator_robots=[_robot_prefix(spec, c.actuator) for c in spec.commands],
        robots=tuple(r.name for r in spec.robots),
        robot_commands=tuple(tuple(int(c) for c in r.commands) for r in spec.robots),
        owners=owners,
        channels=channels,
        outputs=outputs,
        inputs=input_specs,
        lockstep=options.lockstep,
        clock=options.clock,
        startup_check=options.startup_check,
        all_topics=options.all_topics,
        controller_nodes=options.controller_nodes.wanted(namespaces) and manager is not None,
        fleet_services=options.fleet_services,
        ros_args=tuple(options.ros_args),
        sensors=sensors,
        tf=tf,
        actions=actions,
        manager=manager_spec(sim, manager, control_rate) if manager is not None else None,
        wrench_service=wrench.service if wrench is not None and available()["mujoco_ros2_control_msgs"] else "",
        recording=recording,
        view=view,
        randomized=sim.variation is not None,
    )
    return plan, fills, inputs


def _base_velocity_input(sim: Contract) -> Input:
    """The BaseVelocityPlugin's cmd_vel (batchsim.plugins.base_velocity) as an input: a Twist's (or
    TwistStamped's) linear.x, linear.y and angular.z become the world's command, stamped with
    its sim time when the loop takes it (the plugin ignores a TwistStamped's own stamp too)."""
    config = sim.base_velocity.config
    columns = np.array(HELD_DOFS)  # linear x, y and angular z of the input's row

    def apply(worlds: np.ndarray, rows: np.ndarray) -> list[tuple[int, str]]:
        command = rows[:, columns]
        problems = [command_problem(command[k : k + 1]) for k in range(len(worlds))]
        good = np.array([p is None for p in problems], dtype=bool)
        if good.any():
            sim.set_base_velocity(command[good], worlds[good])
        return [(k, p) for k, p in enumerate(problems) if p is not None]

    kind = MessageKind.TWIST_STAMPED if config.use_stamped_twist else MessageKind.TWIST
    return Input(config.cmd_vel_topic, kind, apply)


def _controller_output(out: Output, nworld: int, every: int, channel: Callable[[str, int, ChannelFill], int]) -> OutputSpec:
    """A controller's Output as a channel (its fields side by side) and an OutputSpec."""
    widths = OUTPUT_FIELDS[out.kind]
    sample = out.read()
    layout: list[tuple[str, int, int]] = []  # (field, first column, width)
    at = 0
    for name, width in widths.items():
        if width is None:
            width = len(out.names)
        if name not in sample and out.kind is not MessageKind.JOINT_STATE:
            continue
        layout.append((name, at, width))
        at += width

    def fill(dst: np.ndarray) -> None:
        values = out.read()
        for name, lo, width in layout:
            v = values.get(name)
            if v is None:
                dst[:, lo : lo + width] = np.nan  # a JointState field read() left out this time
            else:
                dst[:, lo : lo + width] = v

    ch = channel(f"{out.topic}", at, fill)
    fields = tuple(Field(name, ch, tuple(range(lo, lo + w))) for name, lo, w in layout)
    return OutputSpec(
        out.topic,
        out.kind.value,
        fields,
        names=tuple(out.names),
        frame_id=out.frame_id,
        child_frame_id=out.child_frame_id,
        covariance=tuple((k, tuple(float(x) for x in v)) for k, v in out.covariance.items()),
        every=every,
        on_request=any(part in f"/{out.topic}/" for part in ON_REQUEST_PARTS),
        state=True,
    )


def describe(plan: FleetPlan, publish_every: int | None = None) -> str:
    """`/world_0 .. /world_15 (publish 100 Hz, QoS reliable depth 10, 2 bridge workers)`."""
    ns = plan.namespaces
    where = worlds_label(ns)
    every = publish_every or next((o.every for o in plan.outputs if o.topic == "joint_states"), 1)
    parts = [f"publish {plan.control_rate / every:g} Hz", f"QoS {plan.reliability.value} depth {plan.qos_depth}"]
    if plan.lockstep:
        parts.append("lockstep")
    if not plan.clock:
        parts.append("no /clock")
    return f"{where} ({', '.join(parts)})"

