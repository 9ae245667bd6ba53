"""`--robot-description-topic`: the URDF comes from a topic, as a ROS launch hands it over
(robot_state_publisher latches it on /robot_description), instead of a file.

The text is fetched by a short-lived ROS process (ros_bridge.worker.description_topic: the
command line itself never imports rclpy), written to a file of its own for the run, and
from then on is what `--ros2-control FILE` would have been: its `<ros2_control>` block, its
`mujoco_model` param, or the URDF itself compiled to MJCF.
"""

from __future__ import annotations

import argparse
import atexit
import math
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from batchsim import startup
from batchsim.cli.args import UsageError


def fetch(args: argparse.Namespace, progress: startup.Progress) -> None:
    """Set `args.ros2_control` to a file holding what `args.robot_description_topic` carries.

    Raises:
      UsageError: with --ros2-control or --no-ros, or no message within the timeout; one line.
    """
    topic = args.robot_description_topic
    if topic is None:
        return
    if args.ros2_control is not None:
        raise UsageError("--robot-description-topic and --ros2-control: give one of them, not both")
    if args.no_ros:
        raise UsageError("--robot-description-topic needs ROS: drop --no-ros")
    wait = args.robot_description_timeout
    if not (math.isfinite(wait) and wait > 0):
        raise UsageError(f"--robot-description-timeout must be a finite number of seconds > 0, got {wait}")
    command = [sys.executable, "-m", "ros_bridge.worker.description_topic", topic, str(args.robot_description_timeout)]
    with progress.stage(f"waiting for the robot description on {topic}"):
        done = subprocess.run(
            [*command, *getattr(args, "ros_args", [])],
            capture_output=True,
            text=True,
            timeout=args.robot_description_timeout + 30,
        )
    if done.returncode != 0:
        why = done.stderr.strip().splitlines()[-1] if done.stderr.strip() else f"exit {done.returncode}"
        domain = os.environ.get("ROS_DOMAIN_ID", "0") or "0"
        raise UsageError(
            f"--robot-description-topic {topic}: {why} (ROS_DOMAIN_ID={domain}; is robot_state_publisher running?)"
        )
    folder = Path(tempfile.mkdtemp(prefix="batchsim-description-"))
    atexit.register(shutil.rmtree, folder, True)
    path = folder / "robot_description.urdf"
    path.write_text(done.stdout)
    args.ros2_control = str(path)
