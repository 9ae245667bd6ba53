"""The bridge workers: the only rclpy code of batchsim.

core.py        the Worker: one rclpy context and node serving a range of worlds
process.py     its process (`python -m ros_bridge.worker ...`, started by ros_bridge/host.py)
messages.py    messages built in bulk as CDR bytes; incoming ones parsed into rows
sensors.py, sensor_messages.py   camera images and lidar scans
services.py    requests to the loop (reset, pause, step) and the services that wait for them
diagnostics.py rejected commands and /diagnostics
conflicts.py   another process already serving these worlds?
"""

from ros_bridge.worker.core import Worker

__all__ = ["Worker"]
