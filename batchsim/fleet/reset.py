"""A reset of one robot of a world of several (batchsim.fleet), leaving the others as they are."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from batchsim.model.interfaces import initial_command
from batchsim.model.spec import RobotPart


def reset_robot(sim: Any, robot: RobotPart, worlds: Sequence[int] | np.ndarray) -> None:
    """Put `robot` back where it starts in the listed worlds: its block of qpos (its keyframe at
    its pose, or its random placement's draw) and of qvel, and its command columns holding that
    pose; every other robot, and every other world, is left as it is. The robot's controllers
    are the manager's to reset (ControllerManager.reset_robot); over ROS, `<ns>/<robot>/reset`
    does both (ros_bridge/simulation.py).

    Raises:
      ValueError: a frozen world (it diverged: reset the whole world), a world out of range.
    """
    rows = np.asarray(worlds, np.int64).reshape(-1)
    frozen = rows[sim.frozen[rows]]
    if frozen.size:
        raise ValueError(f"world {frozen[0]} is frozen (it diverged or overflowed): reset the whole world")
    spec = sim.spec
    start = sim.world_params(rows).get("start_qpos")  # drawn start poses (random placements), if any
    if start is None:
        start = np.broadcast_to(spec.initial.qpos, (len(rows), len(spec.initial.qpos)))
    q0, nq = robot.qpos
    v0, nv = robot.dofs
    qpos, qvel = sim.qstate(rows)
    qpos[:, q0 : q0 + nq] = start[:, q0 : q0 + nq]
    qvel[:, v0 : v0 + nv] = spec.initial.qvel[v0 : v0 + nv]
    held = np.array([initial_command(spec, q) for q in qpos])  # the commands that hold each pose
    sim.command[np.ix_(rows, robot.commands)] = held[:, robot.commands]
    sim.set_qstate(rows, qpos, qvel)
