"""A policy controller's parameters, read from its ros2_control YAML and, where it carries them,
from the ONNX file's own metadata (an mjlab export's `joint_names`, `default_joint_pos`,
`action_scale`, `observation_names`: such a policy needs no hand-written spec):

    arm_reach_controller:
      ros__parameters:
        model: arm_reach.onnx             # from the YAML's folder
        joints: [joint1, joint2, ...]     # the policy's order (default: the export's joint_names)
        default_positions: [0.0, ...]     # the pose actions and joint_pos are relative to
                                          # (default: the export's, else the robot's start pose)
        policy_rate: 50.0                 # Hz, dividing the control rate (default: the control rate)
        inference_threads: 1              # ONNX Runtime's threads (default 1: the physics has the others)
        observations: [joint_pos, joint_vel, command, actions]   # in order (default: the export's)
        terms:                            # per term: scale, clip [lo, hi], history, func
          joint_vel: {scale: 0.1}
        action:
          interface: position             # position (default) or effort
          scale: 0.5                      # a number or one per joint (default: the export's, else 1)
          clip: [-1.0, 1.0]               # the raw action's range (default: none)
        command:
          kind: joint_position            # joint_position: a target per joint; velocity: cmd_vel
          default: [0.0, ...]             # before any arrives (default: the default pose; zero velocity)
          ranges: [[-1.0, 1.0], ...]      # per entry, what `batchsim evaluate` draws each episode

The command comes over ROS per world: `<ns>/<controller>/command` (std_msgs/Float64MultiArray,
joint_position) or `<ns>/<controller>/cmd_vel` (geometry_msgs/Twist: linear.x, linear.y,
angular.z). Everything wrong is a ConfigurationError naming the file, the controller and the key.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from pathlib import Path
from typing import Any

import numpy as np

from batchsim.controllers.base import Params
from batchsim.controllers.policy.terms import FUNCTIONS, KNOWN, Term, function_of, width_of
from batchsim.types import AnyCase


class CommandKind(AnyCase, enum.Enum):
    """What a policy is commanded with, per world."""

    JOINT_POSITION = "joint_position"  # a target position per joint
    VELOCITY = "velocity"  # a base velocity: vx, vy, wz (a cmd_vel Twist)


class ActionInterface(AnyCase, enum.Enum):
    """What a policy's action drives."""

    POSITION = "position"  # target = default + scale * action, to the joints' position interfaces
    EFFORT = "effort"  # effort = scale * action


@dataclasses.dataclass(frozen=True)
class PolicySpec:
    """Everything a PolicyController needs besides the running model.

    Attributes:
      model: the ONNX file.
      joints: the policy's joints, in its order; default: (njoint,) their default pose.
      terms: the observation, in order.
      interface: what the action drives; scale: (njoint,); clip: the raw action's range or None.
      rate: the policy's rate (Hz; None: every control period); the controller divides the
        control rate by it (decimation).
      command: its kind; command_default (ncommand,); command_ranges (ncommand, 2) or None.
    """

    model: Path
    joints: tuple[str, ...]
    default: np.ndarray
    terms: tuple[Term, ...]
    interface: ActionInterface
    scale: np.ndarray
    clip: tuple[float, float] | None
    rate: float | None
    command: CommandKind
    command_default: np.ndarray
    command_ranges: np.ndarray | None

    @property
    def obs_size(self) -> int:
        return sum(t.size for t in self.terms)

    @property
    def command_names(self) -> tuple[str, ...]:
        return (
            self.joints
            if self.command is CommandKind.JOINT_POSITION
            else ("linear.x", "linear.y", "angular.z")
        )


def csv(value: str) -> list[str]:
    """A metadata value as mjlab writes lists: comma-separated."""
    return [v.strip() for v in value.split(",") if v.strip()]


def model_path(params: Params) -> Path:
    """`model`, from the YAML's folder where it is relative."""
    given = Path(params.string("model")).expanduser()
    if given.is_absolute():
        return given
    source = Path(params.where)
    return (source.parent if source.is_file() else Path.cwd()) / given


def read_spec(params: Params, metadata: dict[str, str], start_pose: dict[str, float]) -> PolicySpec:
    """The spec from `params` and the model's `metadata`; `start_pose` maps each joint to where the
    robot starts (the default pose's default)."""
    joints = params.string_list("joints", csv(metadata.get("joint_names", "")) or None, nonempty=True)
    njoint = len(joints)
    default = _vector(
        params,
        "default_positions",
        njoint,
        csv(metadata.get("default_joint_pos", "")) or [start_pose.get(j, 0.0) for j in joints],
    )
    names = params.string_list(
        "observations", csv(metadata.get("observation_names", "")) or None, nonempty=True
    )
    interface = ActionInterface(
        params.choice("action.interface", [i.value for i in ActionInterface], "position")
    )
    meta_scale = csv(metadata.get("action_scale", ""))
    scale = _vector(
        params,
        "action.scale",
        njoint,
        meta_scale if len(meta_scale) == njoint else [float(meta_scale[0]) if meta_scale else 1.0] * njoint,
    )
    clip = _range(params, "action.clip")
    kind = CommandKind(params.choice("command.kind", [k.value for k in CommandKind], "joint_position"))
    ncommand = njoint if kind is CommandKind.JOINT_POSITION else 3
    command_default = _vector(
        params,
        "command.default",
        ncommand,
        list(default) if kind is CommandKind.JOINT_POSITION else [0.0] * 3,
    )
    ranges = params.raw("command.ranges", None)
    command_ranges = None
    if ranges is not None:
        try:
            command_ranges = np.asarray(ranges, dtype=np.float64).reshape(ncommand, 2)
        except (TypeError, ValueError):
            raise params.error(
                "command.ranges", f"one [low, high] per command entry ({ncommand}), got {ranges!r}"
            ) from None
        if not (np.isfinite(command_ranges).all() and (command_ranges[:, 1] >= command_ranges[:, 0]).all()):
            raise params.error("command.ranges", f"finite [low, high] pairs with low <= high, got {ranges!r}")
    terms = []
    for name in names:
        func = function_of(name, params.raw(f"terms.{name}.func", None))
        sensor = name.removeprefix("sensor:") if func == "sensor" else ""
        if func not in FUNCTIONS and func != "sensor":
            origin = "" if params.has("observations") else " (the model's observation_names)"
            raise params.error("observations", f"unknown term {name!r}{origin} (terms: {', '.join(KNOWN)})")
        width = width_of(func, njoint, njoint, ncommand) if func != "sensor" else -1
        history = int(params.number(f"terms.{name}.history", 1, minimum=1))
        terms.append(
            Term(
                name=name,
                func=func,
                width=width,
                scale=np.asarray(params.raw(f"terms.{name}.scale", 1.0), dtype=np.float64),
                clip=_range(params, f"terms.{name}.clip"),
                history=history,
                sensor=sensor,
            )
        )
    rate = params.raw("policy_rate", None)
    if rate is not None:
        rate = params.number("policy_rate", positive=True)
    return PolicySpec(
        model=model_path(params),
        joints=tuple(joints),
        default=np.asarray(default, np.float64),
        terms=tuple(terms),
        interface=interface,
        scale=np.asarray(scale, np.float64),
        clip=clip,
        rate=rate,
        command=kind,
        command_default=np.asarray(command_default, np.float64),
        command_ranges=command_ranges,
    )


def _vector(params: Params, key: str, n: int, default: Any) -> list[float]:
    value = params.raw(key, None)
    value = default if value is None else value
    try:
        out = [float(v) for v in (value if isinstance(value, list | tuple) else [value] * n)]
    except (TypeError, ValueError):
        raise params.error(key, f"{n} numbers, got {value!r}") from None
    if len(out) != n or not all(math.isfinite(v) for v in out):
        raise params.error(key, f"{n} finite numbers (one per joint or command entry), got {value!r}")
    return out


def _range(params: Params, key: str) -> tuple[float, float] | None:
    value = params.raw(key, None)
    if value is None:
        return None
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise params.error(key, f"[low, high], got {value!r}") from None
    if not lo <= hi:
        raise params.error(key, f"[low, high] with low <= high, got {value!r}")
    return lo, hi
