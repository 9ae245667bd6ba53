"""`python -m ros_bridge.worker INDEX WAKE_FD STATUS_FD NOTIFY_FD [--check]` (started by supervisor.py)."""

import os
import sys

from ros_bridge.worker.process import main

code = main()
sys.stdout.flush()
sys.stderr.flush()
os._exit(code)  # all is closed: skip the interpreter's teardown of rclpy and DDS (tenths of a second)
