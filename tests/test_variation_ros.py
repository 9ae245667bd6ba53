"""Each randomized world's draw in /diagnostics (issue 26), over real DDS: `batchsim
--randomize` as a subprocess, the test reads /diagnostics and resets a world through ROS."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import need

rclpy = need("rclpy")  # skips where ROS is absent, fails instead under BATCHSIM_FORCE_BACKENDS=1

from ros_fleet import Fleet, domain_id  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

import batchsim  # noqa: E402
from batchsim.variation import Bound, load  # noqa: E402

pytestmark = pytest.mark.ros


def test_diagnostics_name_each_worlds_draw_and_how_to_reproduce_it(tmp_path):
    source = tmp_path / "randomize.yaml"
    source.write_text(
        "randomize:\n  seed: 9\n  redraw_on_reset: true\n  fields:\n"
        "    - {field: body_mass, names: [link1], scale: {uniform: [0.5, 1.5]}}\n"
    )
    bound = Bound(load(source), batchsim.load("arm").mjmodel)

    def mass(world: int, draw: int) -> str:
        return f"{bound.draw(np.array([world]), np.array([draw]))['body_mass'][0, 2]:.6g}"

    args = ["--worlds", "3", "--world-offset", "10", "--model", "arm", "--randomize", str(source)]
    with Fleet(domain_id(45), args, tmp_path / "batchsim.log") as fleet:
        diag = fleet.diagnostics()
        fleet.wait(lambda: "draw 0" in diag.value("world_11", "randomized"), 40, "world 11's draw in /diagnostics")
        line = diag.value("world_11", "randomized")
        assert line.startswith(f"seed 9, draw 0 (alone: --worlds 1 --world-offset 11 --randomize {source}): ")
        assert f"body_mass link1={mass(11, 0)}" in line
        assert f"link1={mass(12, 0)}" in diag.value("world_12", "randomized")
        assert fleet.call(Trigger, "/world_11/reset", Trigger.Request()).success
        fleet.wait(lambda: "draw 1" in diag.value("world_11", "randomized"), 20, "world 11's second draw")
        assert f"body_mass link1={mass(11, 1)}" in diag.value("world_11", "randomized")
        assert "draw 0" in diag.value("world_12", "randomized")  # the others keep theirs
        assert fleet.close() == 0, fleet.log()
