"""The README's Python and YAML blocks, run the way a user pastes them (issue: every snippet
must run as shown).

Each Python block runs whole in a fresh interpreter from the repository root (a bridge block
on a private ROS domain, LOCALHOST); a block that needs what this machine lacks (PyTorch and
a CUDA GPU) is skipped, naming it. Each YAML block is read by the code that reads such a file:
a `sensors:` block loaded with the model it is shown beside, a PID file through
mujoco_ros2_control's reader. A block of another kind fails the test until it is taught here.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from ros_fleet import LOCALHOST, domain_id, release_domain

ROOT = Path(__file__).resolve().parent.parent
FENCE = re.compile(r"^( *)```(\w+)\n(.*?)^\1```$", re.S | re.M)


def blocks(lang: str) -> list[tuple[int, str]]:
    text = (ROOT / "README.md").read_text()
    out = []
    for m in FENCE.finditer(text):
        if m.group(2) == lang:
            indent = len(m.group(1))
            body = "\n".join(line[indent:] for line in m.group(3).splitlines())
            out.append((text.count("\n", 0, m.start()) + 1, body))
    return out


PYTHON = blocks("python")
YAML = blocks("yaml")


def test_the_readme_has_the_blocks_this_file_runs():
    assert len(PYTHON) >= 4 and len(YAML) >= 2


@pytest.mark.parametrize("line, code", PYTHON, ids=[f"line{n}" for n, _ in PYTHON])
def test_a_python_block_runs_as_shown(line, code):
    missing = [m for m in ("torch",) if re.search(rf"^import {m}\b", code, re.M) and importlib.util.find_spec(m) is None]
    if missing:
        pytest.skip(f"README line {line} needs {', '.join(missing)} (and a CUDA GPU)")
    domain = domain_id(98)
    try:
        env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(domain)}
        done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    finally:
        release_domain(domain)
    assert done.returncode == 0, f"README line {line}:\n{done.stderr[-3000:]}"


@pytest.mark.parametrize("line, text", YAML, ids=[f"line{n}" for n, _ in YAML])
def test_a_yaml_block_is_read_as_shown(line, text, tmp_path):
    import batchsim
    from batchsim.model.params import nest_dotted, node_parameters, read_yaml
    from batchsim.pid import PidGains

    path = tmp_path / "block.yaml"
    path.write_text(text)
    if text.startswith("sensors:"):  # shown beside the rover (its camera, lidar site, wheel sensors)
        sim = batchsim.make("rover", 2, "cpu", sensors=str(path))
        sim.configure()
        assert "ring" in sim.sensors.lidars and sim.scan("ring").shape == (2, 360 * 16)
        sim.shutdown()
    elif "pid_gains" in text:
        params = nest_dotted(node_parameters(read_yaml(path), None, str(path)))
        for mode, joints in params["pid_gains"].items():
            assert mode in ("position", "velocity")
            for joint, values in joints.items():
                _, warnings = PidGains.from_params(values, f"pid_gains.{mode}.{joint}")
                assert not warnings, warnings
    elif "\nrobots:" in "\n" + text:  # a fleet file: its environment beside it as a floor of its own
        from batchsim.fleet import load_fleet

        (tmp_path / "warehouse.xml").write_text('<mujoco><worldbody><geom type="plane" size="5 5 .1"/></worldbody></mujoco>')
        (tmp_path / "arm.yaml").write_text(Path(batchsim.controllers.default_controllers("arm")).read_text())
        (tmp_path / "amr_sensors.yaml").write_text("sensors:\n  camera_resolution: [64, 48]\n")  # as for a rover alone
        spec = load_fleet(path)
        assert len(spec.robots) >= 2 and all(r.state.size for r in spec.robots)
        sized = [r for r in spec.robots if r.sensor_config is not None]
        assert sized and all(spec.sensor_config.cameras[r.prefix + "front_camera"].width == 64 for r in sized)
    elif "\ngroups:" in "\n" + text:  # a fleet of groups: its fleet files and environment beside it, as shipped
        from batchsim.fleet import load_fleet
        from batchsim.fleet.groups import read_groups

        fleets = Path(__file__).resolve().parent.parent / "examples" / "fleets"
        for name in ("arm_and_rover.yaml", "warehouse.xml"):
            (tmp_path / name).write_text((fleets / name).read_text())
        groups = read_groups(path).groups
        assert len(groups) >= 2 and all(len(load_fleet(g.fleet).robots) >= 2 for g in groups)
        assert [g.first_world for g in groups] == [sum(h.worlds for h in groups[:k]) for k in range(len(groups))]
    elif text.startswith("randomize:"):  # shown for the arm (its links, joints, position servos)
        sim = batchsim.make("arm", 3, "cpu", randomize=str(path))
        sim.configure()
        drawn = sim.world_params()
        assert {"body_mass", "geom_friction", "dof_damping", "actuator_gainprm", "opt.gravity", "start_qpos"} <= set(drawn)
        assert not np.array_equal(drawn["body_mass"][0], drawn["body_mass"][1])
        sim.shutdown()
    elif "\n  ros__parameters:\n    model: arm_reach.onnx" in text:  # the shipped policy's block, as shipped
        shipped = Path(__file__).resolve().parent.parent / "examples" / "policies" / "arm_reach.yaml"
        assert read_yaml(path)["arm_reach_controller"] == read_yaml(shipped)["arm_reach_controller"]
    else:
        pytest.fail(f"README line {line}: a YAML block of a kind tests/test_readme.py does not know how to read")
