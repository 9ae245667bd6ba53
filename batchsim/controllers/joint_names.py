"""A message's joint_names onto a controller's joints: the one mapping every trajectory goes
through, from a topic, an action goal or Python (`set_trajectory`).

A JointTrajectory names some or all of the controller's joints in any order; its per-joint
values go to each name's column in the controller's order. An unknown or repeated name is
refused here, with the reason; a joint left out is the controller's business (a partial
goal, `allow_partial_joints_goal`). No ROS here.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


class JointOrder:
    """The controller's joints, in its order: where a message's named joints go."""

    def __init__(self, joints: Sequence[str]):
        self.joints = tuple(joints)
        self._column = {j: k for k, j in enumerate(self.joints)}

    def __len__(self) -> int:
        return len(self.joints)

    def column(self, name: str) -> int | None:
        """The column of joint `name`, or None when the controller has no such joint."""
        return self._column.get(name)

    def problem(self, names: Sequence[str]) -> str | None:
        """Why a message naming `names` cannot be mapped (an unknown or repeated joint), or None."""
        for name in names:
            if name not in self._column:
                return f"unknown joint {name!r} (controller joints: {', '.join(self.joints)})"
        if len(set(names)) != len(names):
            return f"joint_names lists a joint twice: {list(names)}"
        return None

    def columns(self, names: Sequence[str]) -> np.ndarray:
        """(len(names),) intp: each named joint's column; ValueError naming an unknown or
        repeated joint."""
        problem = self.problem(names)
        if problem is not None:
            raise ValueError(problem)
        return np.fromiter((self._column[n] for n in names), dtype=np.intp, count=len(names))

    def mask(self, columns: np.ndarray) -> np.ndarray:
        """(njoint,) bool: the joints a message naming `columns` gives."""
        mask = np.zeros(len(self.joints), bool)
        mask[columns] = True
        return mask
