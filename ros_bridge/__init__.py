"""The ROS 2 bridge: bridge workers serving ranges of worlds, fed through shared memory.

rclpy is imported only by worker.py and messages.py (and by the physics process only when
the bridge runs inside it); plan, memory, commands, requests, host, registry, options,
naming, throttle and transport are plain Python and NumPy.
"""
