"""A multilayer perceptron's weights to an ONNX file a PolicyController runs, with the metadata
an mjlab export carries (joint_names, default_joint_pos, action_scale, observation_names, ...):
how examples/policies/train_arm_reach.py ships its policy, from any library's weights (no
exporter of the training library's own, so the graph is the same whatever trained it).

    export_mlp(path, [(w1, b1), (w2, b2), (w3, b3)], "tanh", {"joint_names": "joint1,joint2"})

The graph: input `obs` (batch, nobs) float32, output `actions` (batch, naction) float32;
`x @ w + b` per layer, the activation between layers, none after the last. Needs the `onnx`
package (the `policy` extra).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

#: activation name -> the ONNX operator
ACTIVATIONS = {"tanh": "Tanh", "relu": "Relu", "elu": "Elu"}


def export_mlp(
    path: str | Path,
    layers: Sequence[tuple[np.ndarray, np.ndarray]],
    activation: str,
    metadata: Mapping[str, str] | None = None,
) -> Path:
    """Write the perceptron of `layers` ((nin, nout) weights, (nout,) bias each) to `path`."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    if activation not in ACTIVATIONS:
        raise ValueError(f"activation {activation!r}: one of {', '.join(ACTIVATIONS)}")
    nodes, weights, x = [], [], "obs"
    for k, (w, b) in enumerate(layers):
        w, b = np.asarray(w, np.float32), np.asarray(b, np.float32).reshape(-1)
        if w.ndim != 2 or w.shape[1] != b.size or (k and w.shape[0] != np.asarray(layers[k - 1][0]).shape[1]):
            raise ValueError(f"layer {k}: weights {w.shape} and bias {b.shape} do not chain")
        weights += [numpy_helper.from_array(w, f"w{k}"), numpy_helper.from_array(b, f"b{k}")]
        last = k == len(layers) - 1
        y = "actions" if last else f"h{k}"
        nodes += [
            helper.make_node("MatMul", [x, f"w{k}"], [f"z{k}"]),
            helper.make_node("Add", [f"z{k}", f"b{k}"], [y if last else f"a{k}"]),
        ]
        if not last:
            nodes.append(helper.make_node(ACTIVATIONS[activation], [f"a{k}"], [y]))
        x = y
    nobs, naction = np.asarray(layers[0][0]).shape[0], np.asarray(layers[-1][0]).shape[1]
    graph = helper.make_graph(
        nodes,
        "policy",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["batch", nobs])],
        [helper.make_tensor_value_info("actions", TensorProto.FLOAT, ["batch", naction])],
        initializer=weights,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], producer_name="batchsim")
    model.ir_version = 8  # ONNX Runtime 1.18 and later read it
    for key, value in (metadata or {}).items():
        model.metadata_props.append(onnx.StringStringEntryProto(key=key, value=str(value)))
    onnx.checker.check_model(model)
    path = Path(path)
    onnx.save(model, path)
    return path


def mlp_forward(
    layers: Sequence[tuple[np.ndarray, np.ndarray]], activation: str, obs: np.ndarray
) -> np.ndarray:
    """The same perceptron in NumPy (float32): what the exported file must compute."""
    act = {
        "tanh": np.tanh,
        "relu": lambda v: np.maximum(v, 0),
        "elu": lambda v: np.where(v > 0, v, np.expm1(v)),
    }[activation]
    x = np.asarray(obs, np.float32)
    for k, (w, b) in enumerate(layers):
        x = x @ np.asarray(w, np.float32) + np.asarray(b, np.float32)
        if k < len(layers) - 1:
            x = act(x)
    return x
