"""Re-simulation: re-run a recorded world's physics from the inputs its recording holds, and say
where it parts from the recorded states. No rclpy and no ROS install: the file is read with mcap.

A recording (`batchsim --record`, ros_bridge/recording.py) carries what re-running needs unless
`--no-record-inputs`: the compiled model (an MJB attachment and its SHA-256), and two topics of
std_msgs/Float64MultiArray (layout.py says their rows):

- `/batchsim/inputs`, one message per control period: the period's number, sim time and physics
  steps, then per recorded world whether it was frozen and what its physics took in the steps
  (ctrl after the PIDs and transmissions; the plugins' held base velocity and xfrc_applied);
- `/batchsim/starts`, in the periods where recorded worlds (re)start (the recording's first
  period, each reset): each such world's whole physics state (mj_getState, mjSTATE_INTEGRATION)
  and its drawn model values (`randomize:`).

    batchsim resim run.mcap --worlds 731         # re-run world 731: bit-exact, or where it parts

recorded.py reads a file; physics.py re-steps one world with raw MuJoCo; compare.py measures
the re-run against the recorded joint states.
"""
