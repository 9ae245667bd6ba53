"""examples/batchsim.launch.py, where ROS's `launch` package is not installed (PyPI has none):
the file's launch description is built against a stand-in of the `launch` API it uses, and
the command line it makes is run for real (issue 23: a launch file for ROS users, tested
where possible without ROS)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import types
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FILE = ROOT / "examples" / "batchsim.launch.py"


class _Recorded:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


def _stand_in_launch() -> dict[str, types.ModuleType]:
    """`launch`, `launch.actions`, `launch.substitutions` with the names the file uses."""
    launch = types.ModuleType("launch")
    actions = types.ModuleType("launch.actions")
    substitutions = types.ModuleType("launch.substitutions")
    launch.LaunchDescription = type("LaunchDescription", (_Recorded,), {})
    for name in ("DeclareLaunchArgument", "ExecuteProcess", "OpaqueFunction"):
        setattr(actions, name, type(name, (_Recorded,), {}))

    class LaunchConfiguration(_Recorded):
        def perform(self, context):
            return context[self.args[0]]

    substitutions.LaunchConfiguration = LaunchConfiguration
    return {"launch": launch, "launch.actions": actions, "launch.substitutions": substitutions}


def _load(monkeypatch) -> types.ModuleType:
    if importlib.util.find_spec("launch") is None:
        for name, module in _stand_in_launch().items():
            monkeypatch.setitem(sys.modules, name, module)
    spec = importlib.util.spec_from_file_location("batchsim_launch", FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_launch_file_declares_batchsims_arguments_and_runs_it(monkeypatch):
    module = _load(monkeypatch)
    description = module.generate_launch_description()
    declared = {a.args[0]: a.kwargs["default_value"] for a in description.args[0][:-1]}
    assert set(module.ARGUMENTS) | {"root_namespace", "extra_args", "batchsim_exe"} == set(declared)
    assert declared["worlds"] == "16"
    if "launch" in sys.modules and not hasattr(sys.modules["launch"], "__file__"):  # the stand-in
        context = {**declared, "worlds": "2", "model": "arm", "backend": "cpu", "root_namespace": "false",
                   "extra_args": "--no-ros --duration 0.2 --quiet"}  # fmt: skip
        process = description.args[0][-1].kwargs["function"](context)[0]
        argv = process.kwargs["cmd"]
        assert argv == ["batchsim", "--worlds", "2", "--model", "arm", "--backend", "cpu", "--no-ros", "--duration", "0.2", "--quiet"]
        done = subprocess.run([sys.executable, "-m", "batchsim.cli", *argv[1:]], capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr


def test_one_world_at_the_root_namespace(monkeypatch):
    module = _load(monkeypatch)
    argv = module.command({"worlds": "1", "root_namespace": "true", "ros2_control": "robot.urdf use_pid:=true"})
    assert argv == ["batchsim", "--worlds", "1", "--ros2-control", "robot.urdf use_pid:=true", "--namespace", ""]
