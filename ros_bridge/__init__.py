"""The ROS 2 bridge: bridge workers serving ranges of worlds, fed through shared memory.

rclpy is imported only by worker/ (the bridge worker processes; in the physics process only
when the bridge runs inside it). Everything else is plain Python and NumPy: `start_bridge`
(bridge; `open_bridge` and `join_bridges` for a fleet of several groups), the plan (plan, outputs, tf_plan, action_plan, manager_link, sensor_topics,
view_plan, recording), the shared-memory protocols (protocol/), the physics side (host,
supervisor, simulation, trajectory_inputs, timeouts, the recording's and the view's
processes), recordings as files (recording_file, view_file), and options, naming,
world_status, registry, throttle, transport. interfaces/ builds the ROS interface packages
PyPI lacks.
"""
