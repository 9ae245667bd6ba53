"""A policy's commands drawn per world, and how far each world is from its command.

Commands are drawn uniformly in the policy's `command.ranges` from the counter-based generator
variation and sensor noise use: world i's k-th command depends only on (seed, i, k), so a world
evaluated alone (`--worlds 1 --world-offset i`) is commanded as it was in the fleet.
"""

from __future__ import annotations

import numpy as np

from batchsim.controllers.policy.spec import CommandKind, PolicySpec
from batchsim.controllers.policy.terms import rotate_into_base
from batchsim.variation import counter_rng

_STREAM = counter_rng.stream_id("batchsim.evaluation.commands")


def draw_commands(ranges: np.ndarray, seed: int, worlds: np.ndarray, counters: np.ndarray) -> np.ndarray:
    """(n, ncommand) commands, uniform in `ranges` (ncommand, 2), for the global world numbers
    `worlds` (n,) at their `counters` (n,) (an episode's number)."""
    keys = counter_rng.world_keys(seed, _STREAM, np.asarray(worlds))
    u = counter_rng.uniform64(
        counter_rng.bits(keys, np.asarray(counters), counter_rng.element_offsets(len(ranges)))
    )
    return ranges[:, 0] + u * (ranges[:, 1] - ranges[:, 0])


def tracking_error(
    policy: PolicySpec, state: np.ndarray, pos_cols: np.ndarray, base: np.ndarray | None, commands: np.ndarray
) -> np.ndarray:
    """(nworld,) each world's distance from its command: the largest joint error (rad or m) of
    a joint-position command; the norm of (vx, vy, wz) in the base frame minus a velocity command."""
    if policy.command is CommandKind.JOINT_POSITION:
        return np.abs(state[:, pos_cols] - commands).max(axis=1)
    if base is None:
        raise ValueError("a velocity command needs a floating base to measure")
    linear = rotate_into_base(base, base[:, 7:10])
    actual = np.concatenate([linear[:, :2], base[:, 12:13]], axis=1)
    return np.linalg.norm(actual - commands, axis=1)
