"""The trajectory controller's parameters that change at run time, per world. No ROS here.

Upstream's JointTrajectoryController re-reads its parameters in `update` once one was set
(generate_parameter_library's `is_old`): the default tolerances (`constraints.*`) for the goals
that come after, the PID gains (`gains.<joint>.*`) at once, and `allow_partial_joints_goal` for
the next goal. batchsim does the same, per world: a set_parameters on
`/world_3/joint_trajectory_controller` changes world 3 alone. Upstream's other parameters are
read-only (`joints`, the interfaces, `interpolation_method`, ...) or ones batchsim accepts and
does not act on (`cmd_timeout`, ...): `refusal` says which and why.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Sequence
from typing import Any

import numpy as np

from batchsim.controllers.trajectory.goals import Constraints
from batchsim.pid import PidGains

#: the PID keys of a `gains.<joint>` block that may be set (control_toolbox's, and the controller's feed-forward)
GAIN_KEYS = (
    "p",
    "i",
    "d",
    "i_clamp_max",
    "i_clamp_min",
    "u_clamp_max",
    "u_clamp_min",
    "antiwindup_strategy",
    "tracking_time_constant",
    "ff_velocity_scale",
)
#: what a set may change, as patterns of the node's parameter names
SETTABLE = (
    "allow_partial_joints_goal",
    "constraints.goal_time",
    "constraints.stopped_velocity_tolerance",
    "constraints.*.trajectory",
    "constraints.*.goal",
    *(f"gains.*.{key}" for key in GAIN_KEYS),
)
#: upstream lets these change at run time; batchsim reads them and does not act on them
NOT_ACTED_ON = (
    "allow_integration_in_goal_trajectories",
    "allow_nonzero_velocity_at_trajectory_end",
    "cmd_timeout",
    "set_last_command_interface_value_as_state_on_activation",
    "gains.*.error_deadband",
)


def settable(key: str, joints: Sequence[str]) -> bool:
    """Whether `key` may be set at run time (a joint's block must name one of `joints`)."""
    if not any(fnmatch.fnmatchcase(key, pattern) for pattern in SETTABLE):
        return False
    parts = key.split(".")
    return len(parts) != 3 or parts[1] in joints


def refusal(name: str, keys: Sequence[str], joints: Sequence[str]) -> str:
    """Why a set of `keys` is refused, naming the first key that may not change; "" if all may."""
    for key in keys:
        if settable(key, joints):
            continue
        if any(fnmatch.fnmatchcase(key, pattern) for pattern in NOT_ACTED_ON):
            why = "batchsim does not act on it (it is accepted from the YAML and ignored)"
        else:
            why = "it is read-only: the controller takes it at start (change the YAML and restart)"
        return f"controller {name!r}: cannot set {key!r} at run time: {why}"
    return ""


def declared(
    joints: Sequence[str], constraints: Constraints, gains: Sequence[PidGains], ff_velocity_scale: np.ndarray, allow_partial: bool
) -> dict[str, Any]:
    """Every settable parameter with its value at start (defaults included, as upstream's node
    declares them): what the controller's node holds beside the YAML's other keys."""
    out: dict[str, Any] = {
        "allow_partial_joints_goal": bool(allow_partial),
        "constraints.goal_time": float(constraints.goal_time),
        "constraints.stopped_velocity_tolerance": float(constraints.stopped_velocity_tolerance),
    }
    for k, joint in enumerate(joints):
        out[f"constraints.{joint}.trajectory"] = float(constraints.trajectory[k])
        out[f"constraints.{joint}.goal"] = float(constraints.goal[k])
        for key in GAIN_KEYS:
            if key == "ff_velocity_scale":
                out[f"gains.{joint}.{key}"] = float(ff_velocity_scale[k])
            elif key == "antiwindup_strategy":
                out[f"gains.{joint}.{key}"] = gains[k].antiwindup_strategy.value
            else:
                out[f"gains.{joint}.{key}"] = float(getattr(gains[k], key))
    return out

