"""A trained policy as a controller: batchsim/PolicyController runs an ONNX policy (mjlab,
Isaac Lab, MuJoCo Playground, or one trained on batchsim's own vector env) on every world at
once, at its own rate, commanded per world over ROS.

    spec.py        its parameters: the YAML's, else the ONNX export's metadata
    terms.py       the observation terms, by mjlab's and Isaac Lab's names
    runtime.py     ONNX Runtime, one batched call for every world (the `policy` extra)
    controller.py  the controller itself
"""

from batchsim.controllers.policy.controller import PolicyController
from batchsim.controllers.policy.spec import ActionInterface, CommandKind, PolicySpec, read_spec
from batchsim.controllers.policy.terms import Context, Observations, Term

__all__ = [
    "ActionInterface",
    "CommandKind",
    "Context",
    "Observations",
    "PolicyController",
    "PolicySpec",
    "Term",
    "read_spec",
]
