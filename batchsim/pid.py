"""PID loops for torque motors, vectorized over worlds: what turns a `position` or `velocity`
command interface on a `motor` (or any effort-type) actuator into `ctrl`.

The gains are read as mujoco_ros2_control reads them (control_toolbox's `PidROS` parameters
under `pid_gains.position.<joint>` / `pid_gains.velocity.<joint>`), and one update is
control_toolbox's `Pid::compute_command(error, dt)`:

    error  = command - measured                      (qpos or qvel of the joint, as read())
    p_term = p * error
    i_term += i * error * dt                        (skipped while dt <= 0)
    i_term  clamped to [i_clamp_min, i_clamp_max]   (the `legacy` anti-windup; infinite by default)
    d_term = d * (error - previous error) / dt      (0 on the first update after a reset;
                                                     d * error_dot where the caller knows it)
    u      = p_term + i_term + d_term, clamped to [u_clamp_min, u_clamp_max]

`conditional_integration` skips the integration while `u` is saturated and the error would
push it further; `back_calculation` bleeds the saturation excess back into `i_term` with
`tracking_time_constant`. Everything is (nworld, npid) float64 NumPy: no per-world Python.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from batchsim.types import AnyCase


class AntiWindup(AnyCase, enum.Enum):
    """control_toolbox's anti-windup strategies (`antiwindup_strategy`, any case)."""

    NONE = "none"
    LEGACY = "legacy"
    BACK_CALCULATION = "back_calculation"
    CONDITIONAL_INTEGRATION = "conditional_integration"


# control_toolbox parameter names that change nothing in simulation (accepted, not warned about)
_ACCEPTED_KEYS = ("antiwindup", "error_deadband", "saturation", "activate_state_publisher")


# PidBank's per-loop arrays, which set_gains makes per world
_GAIN_ARRAYS = ("p", "i", "d", "i_max", "i_min", "u_max", "u_min", "_conditional", "_back", "_tt")


@dataclasses.dataclass(frozen=True)
class PidGains:
    """One joint's PID gains, as control_toolbox's PidROS parameters name them."""

    p: float = 0.0
    i: float = 0.0
    d: float = 0.0
    i_clamp_max: float = math.inf
    i_clamp_min: float = -math.inf
    u_clamp_max: float = math.inf
    u_clamp_min: float = -math.inf
    antiwindup_strategy: AntiWindup = AntiWindup.LEGACY
    tracking_time_constant: float = 0.0

    @classmethod
    def from_params(cls, values: Mapping[str, Any], where: str) -> tuple[PidGains, list[str]]:
        """Gains from a `{p: .., i: .., d: .., u_clamp_max: ..}` mapping.

        Returns the gains and warnings naming keys control_toolbox does not know. Raises
        ValueError (one line naming `where` and the key) for a value that is not a number.
        """
        fields = {f.name for f in dataclasses.fields(cls)}
        kwargs: dict[str, Any] = {}
        warnings = []
        for key, value in values.items():
            if key == "antiwindup_strategy":
                try:
                    kwargs[key] = AntiWindup(str(value))
                except ValueError:
                    raise ValueError(
                        f"{where}.{key}: unknown strategy {value!r} "
                        f"(known: {', '.join(s.value for s in AntiWindup)})"
                    ) from None
            elif key in fields:
                if isinstance(value, bool) or not isinstance(value, int | float) or math.isnan(value):
                    raise ValueError(f"{where}.{key}: must be a number, got {value!r}")
                kwargs[key] = float(value)
            elif key not in _ACCEPTED_KEYS:
                warnings.append(f"{where}.{key}: ignored: not a control_toolbox PID parameter")
        gains = cls(**kwargs)
        if gains.i_clamp_min > gains.i_clamp_max or gains.u_clamp_min > gains.u_clamp_max:
            raise ValueError(f"{where}: a clamp's min is above its max")
        return gains, warnings


class PidBank:
    """`npid` PID loops in each of `nworld` worlds, updated together.

    Attributes:
      gains: the gains of each loop, (npid,) each as arrays.
      i_term: (nworld, npid) float64, the integral term.
      last_error: (nworld, npid) float64, the error of the last update (NaN: none yet).
    """

    def __init__(self, gains: list[PidGains], nworld: int):
        def col(name: str) -> np.ndarray:
            return np.array([getattr(g, name) for g in gains], dtype=np.float64)

        self.gains = gains
        self.p, self.i, self.d = col("p"), col("i"), col("d")
        self.i_max, self.i_min = col("i_clamp_max"), col("i_clamp_min")
        self.u_max, self.u_min = col("u_clamp_max"), col("u_clamp_min")
        strategy = [g.antiwindup_strategy for g in gains]
        self._conditional = np.array([s is AntiWindup.CONDITIONAL_INTEGRATION for s in strategy])
        self._back = np.array([s is AntiWindup.BACK_CALCULATION for s in strategy])
        tt = col("tracking_time_constant")
        # back-calculation's tracking time constant: control_toolbox defaults it to sqrt(d/i) or d/p
        ratio = np.abs(self.d / np.where(self.i > 0, self.i, 1.0))
        self._tt = np.where(tt > 0, tt, np.where(self.i > 0, np.sqrt(ratio), 0.0))
        self._any_conditional, self._any_back = bool(self._conditional.any()), bool(self._back.any())
        self._i_clamped = bool(np.isfinite(self.i_max).any() or np.isfinite(self.i_min).any())
        self._u_clamped = bool(np.isfinite(self.u_max).any() or np.isfinite(self.u_min).any())
        self.i_term = np.zeros((nworld, len(gains)))
        self.last_error = np.full((nworld, len(gains)), np.nan)

    def set_gains(self, worlds: np.ndarray, gains: list[PidGains]) -> None:
        """New gains for the listed worlds' loops (a controller's parameters set at run time),
        from their next update on; the integral and last error are kept, as control_toolbox's
        `set_gains` keeps them. The first call makes every gain an (nworld, npid) array."""
        if not self._per_world:
            for name in _GAIN_ARRAYS:
                setattr(self, name, np.repeat(np.asarray(getattr(self, name))[None], self.i_term.shape[0], axis=0))
        one = PidBank(gains, 1)
        for name in _GAIN_ARRAYS:
            getattr(self, name)[worlds] = getattr(one, name)
        self._any_conditional, self._any_back = bool(self._conditional.any()), bool(self._back.any())
        self._i_clamped = bool(np.isfinite(self.i_max).any() or np.isfinite(self.i_min).any())
        self._u_clamped = bool(np.isfinite(self.u_max).any() or np.isfinite(self.u_min).any())

    @property
    def _per_world(self) -> bool:
        """set_gains made every gain (nworld, npid)."""
        return self.p.ndim == 2

    def _rows(self, worlds: np.ndarray | slice) -> tuple[np.ndarray, ...]:
        """The gains (p, i, d, i_max, i_min, u_max, u_min, conditional, back, tt) of `worlds`:
        per loop, or per world and loop after set_gains."""
        return tuple(getattr(self, n)[worlds] if self._per_world else getattr(self, n) for n in _GAIN_ARRAYS)

    def reset(self, worlds: np.ndarray | slice) -> None:
        """Forget the integral and the last error of the listed worlds (after a reset)."""
        self.i_term[worlds] = 0.0
        self.last_error[worlds] = np.nan

    def reset_columns(self, columns: np.ndarray) -> None:
        """Forget the integral and last error of the listed loops in every world (a loop that
        starts driving its actuator again)."""
        self.i_term[:, columns] = 0.0
        self.last_error[:, columns] = np.nan

    def update(
        self,
        error: np.ndarray,
        dt: np.ndarray | float,
        worlds: np.ndarray | slice = slice(None),
        *,
        error_dot: np.ndarray | None = None,
    ) -> np.ndarray:
        """One update of the listed worlds' loops.

        Args:
          error: (len(worlds), npid) command minus measurement.
          dt: (len(worlds), 1) or (len(worlds),) seconds since each world's last update, or
            one number for every world.
          error_dot: (len(worlds), npid) the error's derivative where the caller knows it (a
            velocity error), as control_toolbox's `compute_command(error, error_dot, dt)`;
            None: the difference quotient of successive errors.
        Returns:
          (len(worlds), npid) the controller outputs u.
        """
        dt = np.asarray(dt, dtype=np.float64).reshape(-1, 1)
        i_term = self.i_term[worlds]
        last = self.last_error[worlds]
        p, i, d, i_max, i_min, u_max, u_min, conditional, back, tt = self._rows(worlds)
        p_term = p * error
        if (dt > 0).all():  # every world stepped since its last update: the usual period
            if error_dot is None:
                d_term = d * np.nan_to_num((error - last) / dt, nan=0.0)  # NaN last: a first update
            integrate = i * error * dt
            elapsed = dt
        else:
            stepped = dt > 0
            elapsed = np.where(stepped, dt, 0.0)
            if error_dot is None:
                safe_dt = np.where(stepped, dt, 1.0)
                d_term = np.where(np.isnan(last) | ~stepped, 0.0, d * (error - last) / safe_dt)
            integrate = i * error * elapsed
        if error_dot is not None:
            d_term = d * error_dot
        if self._any_conditional:
            trial = p_term + i_term + d_term
            saturated = ((trial > u_max) & (error > 0)) | ((trial < u_min) & (error < 0))
            integrate = np.where(conditional & saturated, 0.0, integrate)
        i_term = i_term + integrate
        if self._i_clamped:
            i_term = np.clip(i_term, i_min, i_max)
        u = p_term + i_term + d_term
        out = np.clip(u, u_min, u_max) if self._u_clamped else u
        if self._any_back:
            safe_tt = np.where(tt > 0, tt, 1.0)
            bleed = np.where(tt > 0, (out - u) * elapsed / safe_tt, 0.0)
            i_term = np.where(back, i_term + bleed, i_term)
        self.i_term[worlds] = i_term
        self.last_error[worlds] = error
        return out
