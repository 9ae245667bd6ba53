"""An ONNX policy, run with ONNX Runtime for every world in one call: (nworld, nobs) float32 in,
(nworld, naction) out. onnxruntime is an extra (`pip install 'batchsim[policy]'`), imported
only when a policy is loaded; its CUDA provider is used where it is installed and a GPU is there.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from batchsim.types import ConfigurationError


class PolicyRuntime:
    """The policy in `path` (`where`: the YAML file and key that name it, for messages), run on
    `threads` threads (ONNX Runtime's intra-op pool, not spinning between calls).

    Attributes:
      obs_size, action_size: the model's input and output widths (None where the model leaves
        them symbolic).
      metadata: the model's metadata_props (an mjlab export's joint_names, default_joint_pos,
        action_scale, observation_names, ...), as strings.
      provider: the ONNX Runtime execution provider it runs on.
    """

    def __init__(self, path: Path, where: str, threads: int = 1):
        try:
            import onnxruntime as ort
        except ImportError:
            raise ConfigurationError(
                f"{where}: running an ONNX policy needs onnxruntime: pip install 'batchsim[policy]'"
            ) from None
        if not path.is_file():
            raise ConfigurationError(f"{where}: no such file {str(path)!r}")
        providers = [
            p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in ort.get_available_providers()
        ]
        options = ort.SessionOptions()
        options.log_severity_level = 3  # errors only: its warnings are not the user's
        # one thread that never spins by default: a pool of spinning threads takes the cores the
        # physics threads need, and a small batch gains nothing from it (benchmarks/policy.py)
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        try:
            self.session = ort.InferenceSession(str(path), options, providers=providers)
        except Exception as e:  # InvalidProtobuf, InvalidGraph, ...: one line, the first of its own
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise ConfigurationError(
                f"{where}: {path} is not an ONNX model ONNX Runtime can run ({first})"
            ) from None
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        if len(inputs) != 1 or len(outputs) < 1:
            raise ConfigurationError(
                f"{where}: {path}: a policy takes one input (the observation) and gives the action first; "
                f"this one has {len(inputs)} inputs and {len(outputs)} outputs"
            )
        self._input = inputs[0].name
        self._output = outputs[0].name
        self.obs_size = _width(inputs[0].shape)
        self.action_size = _width(outputs[0].shape)
        self.metadata: dict[str, str] = dict(self.session.get_modelmeta().custom_metadata_map)
        self.provider = self.session.get_providers()[0]

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """The actions of every world's observation `obs` (n, obs_size) float32: (n, action_size) float32."""
        return self.session.run([self._output], {self._input: obs})[0]


def _width(shape: list) -> int | None:
    """The last dimension of an ONNX value's shape, where it is a number."""
    last = shape[-1] if shape else None
    return int(last) if isinstance(last, int) else None
