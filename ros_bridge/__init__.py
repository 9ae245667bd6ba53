"""The ROS 2 bridge: bridge workers serving ranges of worlds, fed through shared memory.

rclpy is imported only by worker/ (the bridge worker processes; in the physics process only
when the bridge runs inside it). Everything else is plain Python and NumPy: the plan (plan,
outputs, tf_plan, action_plan, manager_link), the shared-memory protocol (protocol/), the
physics side (host, supervisor, simulation), registry, options, naming, throttle, transport.
"""
