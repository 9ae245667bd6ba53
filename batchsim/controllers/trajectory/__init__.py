"""joint_trajectory_controller/JointTrajectoryController, over every world at once.

Modules: `controller` (the controller), `timeline` (each world's queued and running
trajectory, and the reference sampled from it), `pool` (the segment pool), `splines`
(segment polynomials and their sampling), `validation` (batch unpacking and checks,
command bounds), `goals` (action goals: tolerances and outcomes), `gains` (the
`gains.<joint>` blocks, read into `batchsim.pid`'s PidGains).

Semantics follow ros2_control's controller:

- A trajectory (trajectory_msgs/JointTrajectory) starts at its header stamp in sim time,
  or at the next update if the stamp is zero. Its points are timed from that start by
  their `time_from_start`, which must be strictly increasing.
- When it starts, the controller inserts the current state (measured position and, if
  the state interfaces have it, velocity; the last reference instead with
  `open_loop_control`) as the point the first segment leaves from.
- Interpolation (`interpolation_method: splines`, the default): linear between points
  that give positions only, cubic where they give velocities too, quintic where they give
  accelerations as well (ros2_control's Trajectory Representation). `none` holds each
  point until the next one's time.
- After the last point the reference holds that point, with zero velocity.
- A new trajectory replaces the current one from its own start time: until then the old
  one keeps running; points already in the past at that time are dropped. A trajectory
  with no points stops the world where it is. A newer trajectory replaces one still
  waiting to start.
- Joints a partial goal (`allow_partial_joints_goal`) leaves out hold their reference.
- Rejected, with a reason and the world unchanged: unknown joints, missing joints unless
  `allow_partial_joints_goal`, non-increasing or negative times, mismatched or non-finite
  values, a trajectory that ends before it would start, more points than
  `max_trajectory_points` (a batchsim parameter, default 10,000), and any value or
  spline between points that would command MAX_COMMAND (1e10) or more, which write()
  would refuse (the check covers what the claimed interfaces get: the position, velocity
  or acceleration reference, or the PID's output from them; the first segment is checked
  as though it left from rest, since the state it leaves from is known only at the start).
  Positions beyond a joint's range are accepted, as upstream accepts them: the actuator's
  ctrlrange and the joint's limit stop the joint, as on a real robot.

At fleet scale trajectories arrive as a `TrajectoryBatch`, one call per period however
many messages came: validation, queueing and the start of every due trajectory are
vectorized over the batch. Points live as given in one flat pool of rows (each row: a
point's time, position, velocity and acceleration), a block per world and trajectory, so
memory follows each world's own trajectory; each world keeps the index of its current
segment, which advances as time does, and that segment's polynomial, made when time
enters it, so queueing costs a copy of the points and sampling O(worlds), not O(points).
The loop keeps the work off the period's critical path where it can: the bridge hands
trajectories over while the device steps (they start at the next update), and
`prepare` (ControllerManager.while_stepping) makes beside the steps the polynomials of
the segments the next update enters, and under open_loop_control (trajectories leave from
the reference, known then) the first segments of the trajectories it starts.

Commands: a `position` interface gets the reference position (and `velocity`, when
claimed alongside it, the reference velocity); a lone `velocity` or `effort` interface
gets `ff_velocity_scale * v_ref + PID(error, velocity error)`, as the stock controller
computes it: `batchsim.pid.PidBank` with the velocity error as the error's derivative, and
`gains.<joint>` holding control_toolbox's PID parameters (`p`, `i`, `d`, the clamps,
`antiwindup_strategy`), the symmetric `i_clamp` and `ff_velocity_scale`.

Action goals (control_msgs/FollowJointTrajectory, served by the ROS bridge) arrive as
trajectories of a TrajectoryBatch with a tag (`goals`) and tolerances; the controller
checks them as upstream does and reports per world `goal`, `outcome` (GoalOutcome) and
`outcome_joint` after each update; `cancel(worlds, goals)` cancels them (goals.py).
"""

from batchsim.controllers.trajectory.controller import (
    COMMAND_COMBINATIONS,
    DEFAULT_MAX_POINTS,
    STATE_COMBINATIONS,
    JointTrajectoryController,
)
from batchsim.controllers.trajectory.goals import Constraints, GoalOutcome
from batchsim.controllers.trajectory.pool import MIN_POOL_ROWS, SPARE_ROWS
from batchsim.controllers.trajectory.splines import Interpolation, Spline

__all__ = [
    "COMMAND_COMBINATIONS",
    "DEFAULT_MAX_POINTS",
    "MIN_POOL_ROWS",
    "SPARE_ROWS",
    "STATE_COMBINATIONS",
    "Constraints",
    "GoalOutcome",
    "Interpolation",
    "JointTrajectoryController",
    "Spline",
]
