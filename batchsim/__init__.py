"""batchsim: N copies of one MuJoCo robot behind a batched ros2_control SystemInterface.

    import batchsim
    sim = batchsim.make("arm", nworld=16, backend="cpu")
    sim.configure(); sim.activate()
    sim.command[:, 0] = 0.5        # joint1/position, every world
    sim.write(); sim.step(10); sim.read()
    sim.state                      # (16, nstate), columns as sim.export_state_interfaces()
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from batchsim.backends import Backend, BackendUnavailable, backend_class, resolve
from batchsim.failures import set_log_dir
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
    "set_log_dir",
]


def make(
    model: str | Path | RobotSpec,
    nworld: int = 1,
    backend: str | Backend = "auto",
    *,
    ros2_control: str | Path | None = None,
    **options: Any,
) -> BatchedSystem:
    """Build `nworld` worlds of `model` on `backend`, initialized (UNCONFIGURED).

    Args:
      model: a shipped model's name ("arm", "car", "quadruped"), a path to an MJCF file,
        or a RobotSpec from `batchsim.load`.
      nworld: number of worlds.
      backend: "cpu", "mjx", "warp", or "auto" (picks one for nworld and the hardware).
      ros2_control: a ros2_control block (file path or XML text) narrowing the interfaces.
      **options: backend options: `nthread` for "cpu"; `nconmax`, `njmax`, `max_data_bytes`,
        `device`, `graph` for "warp"; `device` for "mjx"; `deterministic` for every backend (bitwise-repeatable
        runs: always so on cpu, slower on a GPU). With "auto", those the chosen backend does
        not take are ignored, and `sim.reason` says so.

    Returns:
      The system, in UNCONFIGURED; call configure() and activate() to run it.
    """
    spec = model if isinstance(model, RobotSpec) else load(model, ros2_control=ros2_control)
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
