"""The ROS 2 interface packages that PyPI's ROS 2 Jazzy wheels lack, built pip-only.

PyPI's `ros-jazzy-*` wheels carry rclpy, Fast DDS and the common interfaces, but not
`tf2_msgs`, `control_msgs`, `controller_manager_msgs` nor `mujoco_ros2_control_msgs`.
`definitions/` vendors their upstream `.msg`/`.srv`/`.action` files (field for field, so
every type's RIHS01 hash equals upstream Jazzy's and a batchsim node talks to a real ROS
system), and `python -m ros_bridge.interfaces` (see `build.py`) builds them with cmake +
g++ against the wheels, into the running interpreter's prefix (the venv).

This module only answers "what is there": `available()` and `missing_line()` look for the
packages without importing them (nor rclpy), so the bridge may call them at any time.
"""

from __future__ import annotations

import importlib.util

# the packages, in build order (none depends on another; each depends only on the wheels)
PACKAGES = ("tf2_msgs", "control_msgs", "controller_manager_msgs", "mujoco_ros2_control_msgs")

# what a batchsim node cannot do without each package
LOST = {
    "tf2_msgs": "tf (/tf, /tf_static)",
    "control_msgs": "FollowJointTrajectory/GripperCommand actions",
    "controller_manager_msgs": "controller_manager services",
    "mujoco_ros2_control_msgs": "mujoco_ros2_control services",
}


def available() -> dict[str, bool]:
    """Which of the interface packages this interpreter can import (none is imported)."""
    return {pkg: _importable(pkg) for pkg in PACKAGES}


def missing_line(reason: str = "") -> str | None:
    """The one line to print when some packages are missing; None when all are there.

    `reason` (e.g. "cmake, g++ not found", or the failed stage and its log) is put in
    brackets after the package names. The fix names build tools only where they are not
    on PATH.
    """
    missing = [pkg for pkg, ok in available().items() if not ok]
    if not missing:
        return None
    from ros_bridge.interfaces.build import missing_tools  # stdlib only: cheap

    lost = ", ".join(LOST[pkg] for pkg in missing)
    why = f" ({reason})" if reason else ""
    tools = missing_tools()
    run = "`python -m ros_bridge.interfaces`"
    fix = f"install {', '.join(tools)}, then {run}" if tools else run
    return f"ROS interface packages {', '.join(missing)} missing{why}: no {lost}. Fix: {fix}, or source ROS 2 Jazzy."


def _importable(pkg: str) -> bool:
    try:
        return importlib.util.find_spec(pkg) is not None
    except (ImportError, ValueError):
        return False
