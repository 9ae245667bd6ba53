"""Re-simulation: re-run a recorded world's physics from the inputs its recording holds, and say
where it parts from the recorded states. No rclpy and no ROS install: the file is read with mcap.

A recording (`batchsim --record`, ros_bridge/recording.py) carries what re-running needs unless
`--no-record-inputs`: the compiled model (an MJB attachment and its SHA-256), and three topics
(layout.py says their rows):

- `/batchsim/inputs` (std_msgs/Float64MultiArray), one message per control period: the period's
  number, sim time and physics steps, then per recorded world whether it was frozen, what its
  physics took in the steps (ctrl after the PIDs and transmissions; the plugins' held base
  velocity and xfrc_applied) and its command interfaces;
- `/batchsim/starts` (Float64MultiArray), in the periods where recorded worlds (re)start (the
  recording's first period, each reset): each such world's whole physics state (mj_getState,
  mjSTATE_INTEGRATION), its drawn model values (`randomize:`) and whether it starts afresh;
- `/batchsim/controller_inputs` (std_msgs/String, a JSON document each): every message the
  controllers took (ros_bridge/input_recording.py).

A fleet of several groups (several models) records each group's apart: `/batchsim/<group>/...`,
its model as `batchsim/<group>/model.mjb`, its own metadata record (layout.resim_names).

    batchsim resim run.mcap --worlds 731         # re-run world 731: bit-exact, or where it parts

recorded.py reads a file; physics.py re-steps one world with raw MuJoCo; controllers.py re-runs
it with its controllers too (`--controllers`); compare.py measures a re-run against the
recorded joint states (each robot's, in a world of several), /tf and odometry.
"""
