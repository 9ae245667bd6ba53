"""batchsim: N copies of one MuJoCo robot behind a batched ros2_control SystemInterface.

    import batchsim
    sim = batchsim.make("arm", nworld=16, backend="cpu")
    sim.configure(); sim.activate()
    sim.command[:, 0] = 0.5        # joint1/position, every world
    sim.write(); sim.step(10); sim.read()
    sim.state                      # (16, nstate), columns as sim.export_state_interfaces()
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

# what `batchsim.<name>` is, imported on first use (PEP 562): `import batchsim` and the command's
# `--help` cost no MuJoCo import (issue 46: every command spent seconds importing before it parsed)
_LAZY = {
    "Backend": "batchsim.backends",
    "BackendUnavailable": "batchsim.backends",
    "BatchedSystem": "batchsim.hardware",
    "CallbackReturn": "batchsim.lifecycle",
    "ConfigurationError": "batchsim.types",
    "Contract": "batchsim.contract",
    "Engine": "batchsim.engine",
    "FleetError": "batchsim.fleet",
    "LifecycleError": "batchsim.lifecycle",
    "LifecycleState": "batchsim.lifecycle",
    "ModelError": "batchsim.model",
    "OptionError": "batchsim.types",
    "ReturnType": "batchsim.types",
    "RobotSpec": "batchsim.model",
    "SensorConfig": "batchsim.sensors",
    "SensorConfigError": "batchsim.sensors",
    "Status": "batchsim.types",
    "SystemInterface": "batchsim.lifecycle",
    "Variation": "batchsim.variation",
    "VariationError": "batchsim.variation",
    "build": "batchsim.factory",
    "load": "batchsim.model",
    "load_fleet": "batchsim.fleet",
    "make": "batchsim.factory",
    "make_groups": "batchsim.factory",
    "model_names": "batchsim.model",
    "set_log_dir": "batchsim.parts.failures",
}
# subpackages reached as attributes (`batchsim.controllers.load_controllers` after `import batchsim`)
_SUBMODULES = ("backends", "controllers")

__all__ = [
    "Backend",
    "BackendUnavailable",
    "BatchedSystem",
    "CallbackReturn",
    "ConfigurationError",
    "Contract",
    "Engine",
    "FleetError",
    "LifecycleError",
    "LifecycleState",
    "ModelError",
    "OptionError",
    "ReturnType",
    "RobotSpec",
    "SensorConfig",
    "SensorConfigError",
    "Status",
    "SystemInterface",
    "Variation",
    "VariationError",
    "backends",
    "build",
    "controllers",
    "load",
    "load_fleet",
    "make",
    "make_groups",
    "model_names",
    "set_log_dir",
]

if TYPE_CHECKING:
    from batchsim import backends, controllers
    from batchsim.backends import Backend, BackendUnavailable
    from batchsim.contract import Contract
    from batchsim.engine import Engine
    from batchsim.factory import build, make, make_groups
    from batchsim.fleet import FleetError, load_fleet
    from batchsim.hardware import BatchedSystem
    from batchsim.lifecycle import CallbackReturn, LifecycleError, LifecycleState, SystemInterface
    from batchsim.model import ModelError, RobotSpec, load, model_names
    from batchsim.parts.failures import set_log_dir
    from batchsim.sensors import SensorConfig, SensorConfigError
    from batchsim.types import ConfigurationError, OptionError, ReturnType, Status
    from batchsim.variation import Variation, VariationError


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
    elif name in _SUBMODULES:
        value = importlib.import_module(f"batchsim.{name}")
    else:
        raise AttributeError(f"module 'batchsim' has no attribute {name!r}")
    globals()[name] = value  # once: the next access is a plain attribute
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
