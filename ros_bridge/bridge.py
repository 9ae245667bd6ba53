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
import sys
from collections.abc import Sequence

from batchsim.contract import Contract
from batchsim.controllers import ControllerManager
from batchsim.controllers.topics import Output
from batchsim.loop import SimLoop
from ros_bridge.host import BridgeHost
from ros_bridge.options import BridgeOptions, Reliability, default_workers
from ros_bridge.plan import build_plan
from ros_bridge.recording import Recording
from ros_bridge.registry import ConflictKind
from ros_bridge.sensor_topics import SensorFeed
from ros_bridge.supervisor import FleetConflict, WorkerError
from ros_bridge.view_plan import ViewProcess

__all__ = ["BridgeHost", "BridgeOptions", "ConflictKind", "FleetConflict", "Reliability", "WorkerError", "start_bridge"]


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
    options = options or BridgeOptions()
    workers = options.workers if options.workers is not None else default_workers(sim.nworld)
    workers = min(workers, sim.nworld)
    plan, fills, inputs = build_plan(sim, loop.control_rate, options, manager, max(1, workers), extra_outputs=outputs)
    readers = [c for c in manager if not c.command_interfaces] if manager is not None else []
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
        host.on_close.append(recording.close)
        loop.participants.insert(loop.participants.index(host) + 1, recording)
        if plan.recording.path is not None:
            ok, message = recording.start(plan.recording.path, wait=True)
            if not ok:
                print(f"batchsim: warning: {message}", file=sys.stderr)
    view = None
    if plan.view is not None:  # the web view: a process of its own, reading the snapshot
        view = ViewProcess(plan, host.memory)
        host.on_close.append(view.close)
        if view.url is not None:
            print(f"batchsim: view: {view.url} (the fleet in 3D; a browser elsewhere: --view-host 0.0.0.0, or ssh -L)", file=sys.stderr)
    if plan.sensors is not None:  # cameras and lidars: rendered and scanned right after the host's update
        # a recording wants its cameras too, and the view the camera of the world it shows
        feed = SensorFeed(sim, host.memory, plan.sensors, recording, view.camera if view is not None else None)
        loop.participants.insert(loop.participants.index(host) + 1, feed)
    if manager is not None and manager not in loop.participants:
        loop.participants.append(manager)
    return host
