"""The trajectory controller's `gains.<joint>` blocks, read into `PidGains` for a `PidBank`.

A block holds control_toolbox's PID parameters (`p`, `i`, `d`, `i_clamp_max`, `u_clamp_min`,
`antiwindup_strategy`, ...), read by `PidGains.from_params` exactly as the ros2_control
PID path reads `pid_gains`, and the controller's own: `ff_velocity_scale`, the symmetric
`i_clamp` of ros2_controllers' older releases, and `angle_wraparound` (accepted, not acted
on). Any other key is a warning naming the controller, the joint and the key.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from batchsim.controllers.base import Params
from batchsim.pid import PidGains
from batchsim.types import ConfigurationError

# the controller's own keys of a gains block, beside control_toolbox's
_OWN_KEYS = ("ff_velocity_scale", "i_clamp", "angle_wraparound")


def read_gains(params: Params, joints: Sequence[str], *, effort: bool) -> tuple[list[PidGains], np.ndarray]:
    """Each joint's PID gains, and (njoint,) float64 ff_velocity_scale.

    A joint without a block has zero gains: its velocity interface gets the reference
    velocity (ff_velocity_scale defaults to 1, and to 0 on an effort interface, which needs
    p, i or d). Warnings go to `params.warnings`; a bad value is a ConfigurationError.
    """
    gains = []
    ff_velocity_scale = np.full(len(joints), 0.0 if effort else 1.0)
    for k, joint in enumerate(joints):
        prefix = f"gains.{joint}"
        values = {key[len(prefix) + 1 :]: params.values[key] for key in params.keys_under(prefix)}
        if effort and not any(key in values for key in ("p", "i", "d")):
            raise params.error(
                prefix, "missing: an effort command interface needs PID gains (gains.<joint>.p, .i, .d)"
            )
        if "ff_velocity_scale" in values:
            ff_velocity_scale[k] = params.number(f"{prefix}.ff_velocity_scale")
        if "i_clamp" in values:  # [-i_clamp, i_clamp]; i_clamp_max or i_clamp_min, where given, wins
            clamp = params.number(f"{prefix}.i_clamp", minimum=0.0)
            values.setdefault("i_clamp_max", clamp)
            values.setdefault("i_clamp_min", -clamp)
        toolbox = {key: value for key, value in values.items() if key not in _OWN_KEYS}
        try:
            pid, warnings = PidGains.from_params(
                toolbox, f"{params.where}: controller {params.controller!r}: {prefix}"
            )
        except ValueError as e:
            raise ConfigurationError(str(e)) from None
        for name in ("p", "i", "d"):
            if not math.isfinite(getattr(pid, name)):
                raise params.error(f"{prefix}.{name}", f"must be finite, got {getattr(pid, name)!r}")
        params.warnings += warnings
        gains.append(pid)
    return gains, ff_velocity_scale
