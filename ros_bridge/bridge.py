"""The ROS 2 bridge: every world on its own namespace, served by bridge workers.

    host = start_bridge(sim, loop, BridgeOptions(publish_rate=50), manager)   # serving
    loop.run()
    host.close()

`start_bridge` plans what every world publishes and takes (ros_bridge/plan.py), starts the
workers (processes with their own rclpy context and node, each serving a contiguous range
of worlds; or, with `workers=0`, one worker inside this process), and puts the physics
side (ros_bridge/host.py) first among the loop's participants. The controller manager, if
any, runs as a plain loop participant after it: the host hands it this period's inputs
(trajectory batches, commands, cmd_vel) and publishes its outputs.

Per world, under its namespace `<ns>` (`world_3` from the template `world_{i}`):

    <ns>/joint_states                  sensor_msgs/JointState  (or a joint state broadcaster's)
    <ns>/commands                      std_msgs/Float64MultiArray (subscribed), one value per
                                       command interface in `batchsim info` order
    <ns>/reset                         std_srvs/Trigger: reset this world only
    <ns>/<robot>/reset, <ns>/<robot>/commands
                                       in a world of several robots: reset one robot alone; its own
                                       command vector (batchsim.fleet)
    <ns>/odom                          nav_msgs/Odometry: a floating base
    the controllers' topics            (batchsim/controllers/topics.py)
  created when someone asks (a subscriber, or a publisher for a command topic, appears):
    <ns>/sensors/<sensor>              std_msgs/Float64 or Float64MultiArray (sensor rate)
    <ns>/sensors/<site>/imu            sensor_msgs/Imu: gyro + accelerometer (+ framequat) on one site
    <ns>/sensors/<site>/wrench         geometry_msgs/WrenchStamped: force + torque on one site
    <ns>/actuators/<actuator>/command  std_msgs/Float64 (subscribed)
    <ns>/<camera>/image_raw, depth/image_raw, camera_info; <ns>/scan, <ns>/points
                                       cameras and lidars, rendered only where subscribed
                                       (ros_bridge/sensor_topics.py)
    <ns>/<controller>/controller_state/*

and once per fleet: `/clock` (every control period; worker 0 of the process that has it),
`/diagnostics` (each worker, for its worlds, about twice a second), `/batchsim/reset`,
`/batchsim/pause`, `/batchsim/step`, `/batchsim/record` (an MCAP recording, ros_bridge/recording.py).
"""

from __future__ import annotations

import atexit
import dataclasses
import sys
from collections.abc import Sequence

from batchsim.contract import Contract
from batchsim.controllers import ControllerManager
from batchsim.controllers.topics import Output
from batchsim.loop import OptionError, SimLoop
from ros_bridge.host import BridgeHost
from ros_bridge.input_recording import InputTap
from ros_bridge.options import BridgeOptions, Reliability, default_workers
from ros_bridge.plan import FleetPlan, build_plan
from ros_bridge.recording import Recording
from ros_bridge.registry import ConflictKind
from ros_bridge.sensor_topics import SensorFeed
from ros_bridge.supervisor import FleetConflict, WorkerError
from ros_bridge.view_plan import ViewCamera, ViewProcess, view_camera

__all__ = [
    "BridgeHost", "BridgeOptions", "BridgeParts", "ConflictKind", "FleetConflict", "Reliability", "WorkerError",
    "join_bridges", "open_bridge", "start_bridge",
]  # fmt: skip


@dataclasses.dataclass
class BridgeParts:
    """A bridge `open_bridge` started: its `host` (the loop participant: `close()` ends it all),
    its `recording` (ros_bridge/recording.py; None without one) and its view's camera request
    (`camera`, view_plan.py; None without a view or a camera)."""

    host: BridgeHost
    recording: Recording | None = None
    camera: ViewCamera | None = None

    @property
    def plan(self) -> FleetPlan:
        return self.host.plan


def start_bridge(
    sim: Contract,
    loop: SimLoop,
    options: BridgeOptions | None = None,
    manager: ControllerManager | None = None,
    outputs: Sequence[Output] = (),
) -> BridgeHost:
    """The bridge for `sim` run by `loop`, serving; attached to the loop.

    Args:
      sim: the system, configured.
      loop: the loop (its control rate sets the publish decimation).
      options: see BridgeOptions.
      manager: the controllers; their topics are served, and the manager is appended to
        the loop's participants if it is not there yet.
      outputs: more per-world messages to publish (topics.Output), e.g. a sensor's. Their
        `read()` must return host arrays and not call the system: on a GPU the bridge reads
        them while the device steps the period (BridgeHost.while_stepping).

    Raises:
      OptionError (batchsim.loop): a bad option, named.
      FleetConflict: another process on the ROS domain serves these worlds or /clock.
      WorkerError: a worker could not start.
    """
    parts = open_bridge(sim, loop, options, manager, outputs)
    join_bridges([parts], [""])  # the recording from the first period, the view
    return parts.host


def open_bridge(
    sim: Contract,
    loop: SimLoop,
    options: BridgeOptions | None = None,
    manager: ControllerManager | None = None,
    outputs: Sequence[Output] = (),
) -> BridgeParts:
    """`start_bridge`'s bridge, serving and attached to the loop, but neither recording nor viewed
    yet: `join_bridges` starts those, for this bridge alone or for every group's of a fleet of
    several groups (batchsim.fleet.groups), which are recorded and viewed together. Arguments
    and errors: start_bridge's."""
    options = options or BridgeOptions()
    workers = options.workers if options.workers is not None else default_workers(sim.nworld)
    workers = min(workers, sim.nworld)
    plan, fills, inputs = build_plan(sim, loop.control_rate, options, manager, max(1, workers), extra_outputs=outputs)
    readers = [c for c in manager if not c.command_interfaces] if manager is not None else []
    tap = None  # a recording that keeps inputs keeps what the controllers take too (batchsim resim --controllers)
    if plan.recording is not None and plan.recording.inputs is not None:
        tap = InputTap()
        inputs = tap.wrap(inputs)
    host = BridgeHost(
        sim,
        loop,
        plan,
        fills,
        inputs,
        processes=workers > 0,
        command_timeout=options.command_timeout,
        lockstep_timeout=options.lockstep_timeout,
        readers=readers,
        manager=manager,
    )
    # rclpy aborts a process whose context is still up at exit: close even if the run fails
    atexit.register(host.close)
    host.start()
    host.attach()
    recording = None
    if plan.recording is not None:  # MCAP: with --record from the first period, else on request
        recording = Recording(plan, host.memory, loop)
        if tap is not None:
            tap.target = recording.inputs
            if host.manager_link is not None:
                host.manager_link.tap = tap
        host.on_close.append(recording.close)
        loop.participants.insert(loop.participants.index(host) + 1, recording)
    # the web view's camera request: each browser's picked world's camera, rendered as if subscribed
    camera = view_camera(host.memory) if plan.view is not None else None
    if plan.sensors is not None:  # cameras and lidars: rendered and scanned right after the host's update
        # a recording wants its cameras too, and the view the camera of each world its browsers show
        feed = SensorFeed(sim, host.memory, plan.sensors, recording, camera)
        loop.participants.insert(loop.participants.index(host) + 1, feed)
    if manager is not None and manager not in loop.participants:
        loop.participants.append(manager)
    return BridgeParts(host, recording, camera)


def join_bridges(bridges: Sequence[BridgeParts], names: Sequence[str]) -> ViewProcess | None:
    """Record and view `bridges` together: one bridge's (`names` [""]), or every group's of a fleet
    of several groups, the first group's first (`names`, the groups'). The first bridge's recording
    leads the others' (ros_bridge/recording.py: one recorder, one file of every group's worlds),
    recording from the first period where --record gave a file; one view process shows every
    bridge's worlds (where the first bridge's options ask for the view). The view's process, or None.

    Raises:
      OptionError: `record_topics` names a topic no group of the recorded worlds publishes.
    """
    if len(names) != len(bridges):
        raise ValueError(f"join_bridges: {len(names)} names for {len(bridges)} bridges")
    first = bridges[0]
    recordings = [b.recording for b in bridges if b.recording is not None]
    if len(bridges) > 1:
        unknown = [set(r.spec.unknown) for r in recordings]
        missing = sorted(set.intersection(*unknown)) if unknown else []
        if missing:
            raise OptionError("record_topics", f"names {missing[0]!r}, which no group of the recorded worlds publishes")
    leader = first.recording
    if leader is not None:
        followers = [(name, b.recording) for b, name in zip(bridges[1:], names[1:], strict=True) if b.recording is not None]
        leader.lead([r for _, r in followers], [names[0], *(name for name, _ in followers)])
        for b in bridges[1:]:  # whichever bridge closes first ends the recording, while every ring is there
            b.host.on_close.insert(0, leader.close)
        if leader.spec.path is not None:
            ok, message = leader.start(leader.spec.path, wait=True)
            if not ok:
                print(f"batchsim: warning: {message}", file=sys.stderr)
    view = None
    if first.plan.view is not None:  # the web view: a process of its own, reading the snapshots
        viewed = [b for b in bridges if b.plan.view is not None]
        view = ViewProcess([b.plan for b in viewed], [b.camera for b in viewed])
        first.host.on_close.append(view.close)
        first.host.workers.watchers.append(view.watch)
        for b in bridges[1:]:  # whichever bridge closes first ends the view, while every snapshot is there
            b.host.on_close.insert(0, view.close)
        if view.url is not None:
            print(f"batchsim: view: {view.url} (the fleet in 3D; a browser elsewhere: --view-host 0.0.0.0, or ssh -L)", file=sys.stderr)
    return view
