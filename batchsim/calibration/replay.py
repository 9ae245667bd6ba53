"""The real bag replayed into N worlds in lockstep, and each world's error per joint.

Every world starts where the real robot's first joint state was (at rest there: the position
commands hold it), under the controllers the robot ran (a controller_manager YAML). Each control
period the bag's commands that had arrived by then go into those controllers for every world
through the controllers' own inputs (`Controller.topics()`: what the ROS bridge hands a
Float64MultiArray or a JointTrajectory to), before the controllers' update. Each world's
joint positions are compared with the real ones at the real joint states' stamps (linear
between the periods around a stamp): the error per world and joint is the RMS over the bag.

    errors = replay_worlds("arm", 256, "cpu", variation, bag, "controllers.yaml")
    errors.rms        (256, njoint) rad or m; inf in a world that diverged
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from batchsim.calibration.bag import BagError, Command, RealBag
from batchsim.controllers.manager import ControllerManager
from batchsim.controllers.topics import Input, MessageKind, trajectory_batch
from batchsim.loop import Participant, SimLoop
from batchsim.types import FROZEN
from batchsim.variation import Variation

#: a stamp this close after a period's time counts as that period's (sim time adds up periods)
_EPS = 1e-9


def controller_inputs(manager: ControllerManager) -> dict[str, Input]:
    """Every command topic of the manager's controllers (relative to a namespace) -> its Input."""
    out: dict[str, Input] = {}
    for controller in manager:
        for inp in controller.topics().inputs:
            if inp.kind in (MessageKind.FLOAT64_MULTI_ARRAY, MessageKind.JOINT_TRAJECTORY):
                out[inp.topic] = inp
    return out


@dataclasses.dataclass(frozen=True)
class WorldErrors:
    """Each world's tracking of the real robot.

    Attributes:
      rms: (nworld, njoint) float64, the RMS position error per joint over the bag; inf where
        the world diverged.
      joints: the bag's joints, the columns of `rms`.
      params: each world's drawn values (sim.world_params()).
      draws: (nworld, k) the draws of each entry of the Variation (one value each), or None.
    """

    rms: np.ndarray
    joints: tuple[str, ...]
    params: dict[str, np.ndarray]
    draws: np.ndarray | None

    @property
    def overall(self) -> np.ndarray:
        """(nworld,) the RMS over joints and samples."""
        return np.sqrt(np.mean(self.rms**2, axis=1))


class Replay(Participant):
    """A loop participant (before the controller manager): the bag's due commands into every
    world's controllers, and every world's error at the bag's joint-state stamps."""

    def __init__(self, bag: RealBag, inputs: Mapping[str, Input], state_names: list[str], nworld: int):
        self.bag, self.inputs, self.nworld = bag, inputs, nworld
        self._cols = np.array([state_names.index(f"{j}/position") for j in bag.joints])
        self._worlds = np.arange(nworld, dtype=np.int64)
        self.squared = np.zeros((nworld, len(bag.joints)))
        self.count = np.zeros(len(bag.joints))
        self._sample = 0
        self._command = 0
        self._before: tuple[float, np.ndarray] | None = None

    @property
    def done(self) -> bool:
        return self._sample >= len(self.bag.times)

    def update(self, sim: Any, time: float, period: float) -> None:
        position = sim.state[:, self._cols]
        bag = self.bag
        while self._sample < len(bag.times) and bag.times[self._sample] <= time + _EPS:
            stamp, real = bag.times[self._sample], bag.positions[self._sample]
            if self._before is None or stamp >= time - _EPS:
                sim_pos = position
            else:
                t0, p0 = self._before
                w = (stamp - t0) / (time - t0)
                sim_pos = p0 + w * (position - p0)
            seen = np.isfinite(real)
            error = np.where(seen, sim_pos - np.where(seen, real, 0.0), 0.0)
            self.squared += error**2
            self.count += seen
            self._sample += 1
        self._before = (time, position.copy())
        while self._command < len(bag.commands) and bag.commands[self._command].time <= time + _EPS:
            self._apply(bag.commands[self._command])
            self._command += 1

    def _apply(self, command: Command) -> None:
        inp = self.inputs[command.topic]
        where = f"{self.bag.path}: {self.bag.namespace}/{command.topic} at {command.time:.3f} s"
        if command.kind is MessageKind.FLOAT64_MULTI_ARRAY:
            assert command.data is not None
            if len(command.data) != inp.width:
                raise BagError(f"{where}: {len(command.data)} values, the controller takes {inp.width}")
            rejected = inp.apply(self._worlds, np.tile(command.data, (self.nworld, 1)))
        else:
            if command.positions is None:
                raise BagError(f"{where}: a trajectory point's positions do not match its joint_names")
            message = (
                command.joint_names,
                command.point_times,
                command.positions,
                command.velocities,
                command.accelerations,
                command.start,
            )
            batch, _, rejected = trajectory_batch(inp.joints, [(w, *message) for w in range(self.nworld)])
            if not rejected:
                rejected = inp.apply(batch)
        if rejected:
            raise BagError(f"{where}: refused by its controller: {rejected[0][1]}")

    def rms(self) -> np.ndarray:
        """(nworld, njoint) the RMS error so far (NaN for a joint never compared)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.sqrt(self.squared / self.count)


def replay_worlds(
    model: str | Path,
    nworld: int,
    backend: str,
    variation: Variation | None,
    bag: RealBag,
    controllers: str | Path | Mapping[str, Any],
) -> WorldErrors:
    """Replay `bag` into `nworld` worlds of `model` drawn from `variation` (None: the model as it is)."""
    import batchsim
    from batchsim.controllers import load_controllers

    sim = batchsim.make(model, nworld, backend, randomize=variation)
    sim.configure()
    sim.activate()
    manager = load_controllers(controllers, sim.spec, nworld)
    _start_at(sim, bag)
    replay = Replay(bag, controller_inputs(manager), list(sim.export_state_interfaces()), nworld)
    loop = SimLoop(sim, control_rate=manager.update_rate, rtf=0, participants=[replay, manager])
    nperiod = math.ceil(bag.duration / loop.period - 1e-6) + 1
    for _ in range(nperiod):
        loop.run_period()
    rms = replay.rms()
    rms[(sim.status & np.uint8(FROZEN)) != 0] = np.inf
    params = sim.world_params()
    draws = None
    bound = sim.variation_bound
    if bound is not None:
        draws = np.stack([d[:, 0, 0] for d in bound.entry_draws(np.arange(nworld), sim.draw_numbers())], axis=1)
    return WorldErrors(rms, bag.joints, params, draws)


def _start_at(sim: Any, bag: RealBag) -> None:
    """Every world at the bag's first joint positions (and velocities), its position commands holding them."""
    first = bag.positions[0]
    qpos, qvel = sim.qstate()
    velocity = bag.velocities[0] if bag.velocities is not None else np.zeros(len(bag.joints))
    joints = {j.name: j for j in sim.spec.joints}
    commands = list(sim.export_command_interfaces())
    for k, name in enumerate(bag.joints):
        if not np.isfinite(first[k]):
            continue
        joint = joints[name]
        qpos[:, joint.qposadr] = first[k]
        qvel[:, joint.dofadr] = velocity[k] if np.isfinite(velocity[k]) else 0.0
        if f"{name}/position" in commands:
            sim.command[:, commands.index(f"{name}/position")] = first[k]
    sim.set_qstate(None, qpos, qvel)
