"""batchsim: N copies of one MuJoCo robot behind a batched ros2_control SystemInterface.

    import batchsim
    sim = batchsim.make("arm", nworld=16, backend="cpu")
    sim.configure(); sim.activate()
    sim.command[:, 0] = 0.5        # joint1/position, every world
    sim.write(); sim.step(10); sim.read()
    sim.state                      # (16, nstate), columns as sim.export_state_interfaces()
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from batchsim.backends import Backend, BackendUnavailable, backend_class, resolve
from batchsim.hardware import (
    BatchedSystem,
    CallbackReturn,
    ConfigurationError,
    LifecycleError,
    LifecycleState,
    ReturnType,
    Status,
    SystemInterface,
)
from batchsim.model import ModelError, RobotSpec, load, model_names

__all__ = [
    "Backend",
    "BackendUnavailable",
    "BatchedSystem",
    "CallbackReturn",
    "ConfigurationError",
    "LifecycleError",
    "LifecycleState",
    "ModelError",
    "ReturnType",
    "RobotSpec",
    "Status",
    "SystemInterface",
    "load",
    "make",
    "model_names",
]


def make(
    model: str | Path | RobotSpec,
    nworld: int = 1,
    backend: str | Backend = "auto",
    *,
    ros2_control: str | Path | None = None,
    keyframe: str | int | None = None,
    **options: Any,
) -> BatchedSystem:
    """Build `nworld` worlds of `model` on `backend`, initialized (UNCONFIGURED).

    Args:
      model: a shipped model's name ("arm", "car", "quadruped"), a path to an MJCF file,
        or a RobotSpec from `batchsim.load`.
      nworld: number of worlds.
      backend: "cpu", "mjx", "warp", or "auto" (picks one for nworld and the hardware).
      ros2_control: a robot description whose ros2_control blocks narrow the interfaces: a
        URDF/xacro/XML file path (xacro arguments may follow: "robot.urdf.xacro use_pid:=true")
        or XML text.
      keyframe: the keyframe (name or index) every world starts in and `reset` returns to;
        None: the block's `initial_keyframe`, else `home` when the model has one, else qpos0.
      **options: backend options: `nthread` for "cpu"; `nconmax`, `njmax`, `device`, `graph`
        for "warp"; `device` for "mjx"; `deterministic` for every backend (bitwise-repeatable
        runs: always so on cpu, slower on a GPU). With "auto", those the chosen backend does
        not take are ignored, and `sim.reason` says so.

    Returns:
      The system, in UNCONFIGURED; call configure() and activate() to run it.
    """
    if isinstance(model, RobotSpec):
        if ros2_control is not None or keyframe is not None:
            raise ValueError("a RobotSpec is already loaded: give ros2_control= and keyframe= to batchsim.load")
        spec = model
    else:
        spec = load(model, ros2_control=ros2_control, keyframe=keyframe)
    for warning in spec.warnings:  # what the description asks for and batchsim does not act on
        logging.getLogger("batchsim").warning("batchsim: warning: %s", warning)
    chosen, reason = resolve(backend, spec, nworld)
    cls = backend_class(chosen)
    if Backend.parse(backend) is Backend.AUTO:
        # options meant for a backend auto did not pick (nconmax for warp) are dropped, and said so
        ignored = sorted(set(options) - set(cls.OPTIONS))
        options = {k: v for k, v in options.items() if k in cls.OPTIONS}
        if ignored:
            reason += f"; ignored {', '.join(ignored)}, which {chosen.value} does not take"
    sim = cls(spec, nworld, **options)
    sim.reason = reason
    sim.initialize()
    return sim
