"""The rclpy twins of the `ros2` recipes of docs/ros.md and the README (issue 46: the pip install
has no `ros2` CLI): examples/controllers.py (list, switch, a FollowJointTrajectory goal) and
examples/fleet_services.py (reset, pause, step, resume, record), each run as a user runs it, in a
process of its own, against a batchsim fleet of the arm over real DDS. Domain 68.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import need
from ros_fleet import LOCALHOST, Fleet, domain_id

need("rclpy")
pytestmark = pytest.mark.ros

EXAMPLES = Path(__file__).parent.parent / "examples"


def _run(fleet: Fleet, script: str, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(fleet.domain)}
    return subprocess.run([sys.executable, str(EXAMPLES / script), *args], capture_output=True, text=True, timeout=120, env=env)


def test_the_ros_recipes_run_with_rclpy_alone(tmp_path):
    args = ["--worlds", "4", "--controllers", "default", "--record", str(tmp_path / "first.mcap")]
    with Fleet(domain_id(68), args, tmp_path / "batchsim.log") as fleet:
        fleet.wait_started()
        listed = _run(fleet, "controllers.py", "list", "--world", "2")
        assert listed.returncode == 0, listed.stderr
        assert "joint_trajectory_controller" in listed.stdout and "active" in listed.stdout
        off = _run(fleet, "controllers.py", "switch", "--world", "2", "--deactivate", "joint_trajectory_controller")
        assert off.returncode == 0 and off.stdout.strip() == "ok", off.stdout + off.stderr
        assert "inactive" in _run(fleet, "controllers.py", "list", "--world", "2").stdout
        on = _run(fleet, "controllers.py", "switch", "--world", "2", "--activate", "joint_trajectory_controller")
        assert on.returncode == 0, on.stdout + on.stderr
        goal = _run(fleet, "controllers.py", "goal", "--world", "2", "--seconds", "0.5")
        assert goal.returncode == 0 and "status 4 error_code 0" in goal.stdout, goal.stdout + goal.stderr
        assert "feedback:" in goal.stdout
        got = _run(fleet, "controllers.py", "param", "--world", "2", "--name", "constraints.goal_time")
        assert got.returncode == 0 and got.stdout.strip() == "constraints.goal_time: 0.0", got.stdout + got.stderr
        put = _run(fleet, "controllers.py", "param", "--world", "2", "--name", "constraints.goal_time", "--value", "0.5")
        assert put.returncode == 0 and put.stdout.strip() == "constraints.goal_time: 0.5", put.stdout + put.stderr
        bad = _run(fleet, "controllers.py", "param", "--world", "2", "--name", "interpolation_method", "--value", "none")
        assert bad.returncode == 1 and "read-only" in bad.stdout, bad.stdout + bad.stderr
        for what, expected in (
            (["reset", "--world", "1"], "/world_1/reset: ok"),
            (["pause"], "/batchsim/pause: ok: paused"),
            (["step"], "/batchsim/step: ok: stepped to sim time"),
            (["resume"], "/batchsim/pause: ok: running"),
            (["reset"], "/batchsim/reset: ok"),
            (["stop-recording"], "/batchsim/record: ok"),
            (["record"], "/batchsim/record: ok: recording to"),
            (["stop-recording"], "/batchsim/record: ok"),
        ):
            out = _run(fleet, "fleet_services.py", *what)
            assert out.returncode == 0 and expected in out.stdout, (what, out.stdout, out.stderr)
