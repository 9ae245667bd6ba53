"""A policy controller run over every world for a number of episodes, each world commanded with
its own seeded draw, and what each world did: `batchsim evaluate`'s measurements.

Episode k of world i: the world's k-th draw of its randomized conditions (a reset at each
episode after the first, `redraw_on_reset`), the k-th command of world i (commands.py), then
`seconds` of the loop at full speed. Measured per world and episode, from each period's read:
the error (commands.tracking_error) over time, success (the error below `tolerance` at the
end), the tracking error (its mean over the episode's last quarter), the time to target
(the first period below `tolerance`; NaN: never) and a fall (the world diverged, or a floating
base dropped below `fall_height`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from batchsim.controllers.manager import ControllerManager
from batchsim.controllers.policy.controller import PolicyController
from batchsim.evaluation.commands import draw_commands, tracking_error
from batchsim.loop import SimLoop
from batchsim.types import FROZEN, ConfigurationError
from batchsim.variation.report import changes


@dataclasses.dataclass(frozen=True)
class EvalOptions:
    """How the policy is evaluated: `episodes` of `seconds` each, success within `tolerance`
    (rad or m of a joint target; m/s and rad/s of a velocity command), commands drawn from
    `seed`, a fall below `fall_height` (m; None: only a diverged world falls)."""

    episodes: int = 3
    seconds: float = 3.0
    tolerance: float = 0.1
    seed: int = 0
    fall_height: float | None = None


@dataclasses.dataclass
class Results:
    """Per world (rows) and episode (columns); `worlds` are the fleet's world numbers
    (world_offset + row), so a row is reproduced alone with `--worlds 1 --world-offset W`.

    Attributes:
      commands: (n, E, ncommand) what each world was commanded.
      draws: (n, E) the draw number of each episode's conditions.
      params: [n][E] each episode's drawn values in words ("" without a variation).
      success, fell: (n, E) bool.
      final_error, tracking_error, time_to_target: (n, E) float64 (time: NaN where never).
      error_trace: (nperiod, n) float32, the error of each period of the last episode.
      period: the control period (s).
    """

    worlds: np.ndarray
    commands: np.ndarray
    draws: np.ndarray
    params: list[list[str]]
    success: np.ndarray
    fell: np.ndarray
    final_error: np.ndarray
    tracking_error: np.ndarray
    time_to_target: np.ndarray
    error_trace: np.ndarray
    period: float
    options: EvalOptions

    @property
    def success_rate(self) -> float:
        return float(self.success.mean())

    def world_success(self) -> np.ndarray:
        """(n,) each world's success rate over its episodes."""
        return self.success.mean(axis=1)

    def worst(self, count: int) -> np.ndarray:
        """Rows of the `count` worst worlds: fewest successes, then largest tracking error."""
        order = np.lexsort((-np.nanmean(self.tracking_error, axis=1), self.world_success()))
        return order[:count]


def find_policy(manager: ControllerManager, name: str | None) -> PolicyController:
    """The manager's policy controller (`name` where it has several)."""
    policies = [c for c in manager if isinstance(c, PolicyController)]
    if name is not None:
        policies = [c for c in policies if c.name == name]
    if len(policies) != 1:
        names = ", ".join(c.name for c in manager if isinstance(c, PolicyController)) or "none"
        which = f"no policy controller named {name!r}" if name else "one policy controller to evaluate"
        raise ConfigurationError(f"{manager.source}: {which} (policy controllers: {names})")
    policy = policies[0]
    if policy.policy.command_ranges is None:
        raise ConfigurationError(
            f"{manager.source}: controller {policy.name!r}: command.ranges: needed to evaluate (the range "
            "each command entry is drawn from, [[low, high], ...])"
        )
    return policy


def run_episodes(
    sim: Any,
    manager: ControllerManager,
    loop: SimLoop,
    policy: PolicyController,
    options: EvalOptions,
    world_offset: int = 0,
) -> Results:
    """Every world of `sim` through `options.episodes` episodes under `manager` in `loop`
    (rtf 0), commanded in-process through the policy's `set_commands`."""
    n, spec = sim.nworld, policy.policy
    worlds = world_offset + np.arange(n)
    nperiod = max(1, round(options.seconds / loop.period))
    names = sim.export_state_interfaces()
    pos = np.array([names.index(f"{j}/position") for j in spec.joints])
    shape = (n, options.episodes)
    commands = np.zeros((*shape, len(spec.command_default)))
    draws = np.zeros(shape, np.int64)
    params: list[list[str]] = [[] for _ in range(n)]
    success, fell = np.zeros(shape, bool), np.zeros(shape, bool)
    final, tracking, reach = np.zeros(shape), np.zeros(shape), np.full(shape, np.nan)
    trace = np.zeros((nperiod, n), np.float32)
    settle = max(1, nperiod // 4)
    for e in range(options.episodes):
        if e:
            loop.reset(None)  # every world's next draw, and the controllers start over
        draws[:, e] = sim.draw_numbers()
        for row, lines in enumerate(_drawn(sim)):
            params[row].append(lines)
        commands[:, e] = draw_commands(spec.command_ranges, options.seed, worlds, np.full(n, e))
        rejected = policy.set_commands(np.arange(n), commands[:, e])
        if rejected:
            raise ConfigurationError(
                f"{manager.source}: controller {policy.name!r}: a drawn command was refused: {rejected[0][1]}"
            )
        down = np.zeros(n, bool)
        for k in range(nperiod):
            loop.run_period()
            trace[k] = tracking_error(spec, sim.state, pos, sim.base_state, commands[:, e])
            down |= (sim.status & np.uint8(FROZEN)) != 0
            if options.fall_height is not None and sim.base_state is not None:
                down |= sim.base_state[:, 2] < options.fall_height
        below = trace < options.tolerance
        first = np.where(below.any(axis=0), below.argmax(axis=0), -1)
        reach[:, e] = np.where(first >= 0, (first + 1) * loop.period, np.nan)
        final[:, e] = trace[-1]
        tracking[:, e] = trace[-settle:].mean(axis=0)
        fell[:, e] = down
        success[:, e] = below[-1] & ~down
    return Results(
        worlds, commands, draws, params, success, fell, final, tracking, reach, trace, loop.period, options
    )


def _drawn(sim: Any) -> list[str]:
    """Each world's current draw in words: the fields that differ from the model's own."""
    bound = sim.variation_bound
    if bound is None:
        return [""] * sim.nworld
    values = sim.world_params()
    return ["; ".join(changes(bound, sim.model, values, row)) for row in range(sim.nworld)]
