"""batchsim/PolicyController: an ONNX policy run as a ros2_control controller over every world.

Each policy period (`policy_rate`, dividing the control rate) it builds every world's
observation from the declared terms (terms.py), runs one batched inference for all worlds
(runtime.py), and turns the actions into joint targets: `default + scale * action` to the
joints' position interfaces, or `scale * action` to their effort interfaces. Between policy
periods the targets are held. Its parameters are spec.py's; its command comes per world over
ROS (`<ns>/<controller>/command` or `<ns>/<controller>/cmd_vel`) or from `set_commands`.

A world whose policy output holds NaN or inf keeps its last action: its command row is
written as NaN, so the contract's write() gives that world BAD_COMMAND and keeps its previous
ctrl, and no other world is touched; one log line names the controller and the worlds.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np

from batchsim.controllers.base import Controller, Params, last_per_world, rows_all
from batchsim.controllers.policy.runtime import PolicyRuntime
from batchsim.controllers.policy.spec import ActionInterface, CommandKind, PolicySpec, model_path, read_spec
from batchsim.controllers.policy.terms import Context, Observations, Term
from batchsim.controllers.topics import ControllerTopics, Input, MessageKind, Rejections
from batchsim.model import RobotSpec
from batchsim.types import MAX_COMMAND

log = logging.getLogger("batchsim.controllers.policy")

#: the Twist columns a velocity command takes: linear.x, linear.y, angular.z
_TWIST_COLUMNS = np.array([0, 1, 5])


class PolicyController(Controller):
    """batchsim/PolicyController: the parameters spec.py describes.

    Attributes:
      policy: the spec read from the YAML and the model's metadata.
      runtime: the ONNX Runtime session.
      actions: (nworld, njoint) float32, each world's last finite raw action.
      targets: (nworld, njoint) float64, what is written to the claimed interfaces.
      commands: (nworld, ncommand) float64, each world's command.
      bad: (nworld,) bool, worlds whose last policy output was not finite.
    """

    TYPE: ClassVar[str] = "batchsim/PolicyController"

    def __init__(self, name: str, params: Params, spec: RobotSpec, nworld: int):
        super().__init__(name, params, spec, nworld)
        threads = int(params.number("inference_threads", 1, minimum=1))
        self.runtime = PolicyRuntime(model_path(params), f"{params.where}: controller {name!r}: model", threads)
        start = spec.initial.qpos if spec.initial is not None else spec.mjmodel.qpos0
        start_pose = {j.name: float(start[j.qposadr]) for j in spec.joints}
        policy = read_spec(params, self.runtime.metadata, start_pose)
        self.check_joints("joints", policy.joints)
        policy = dataclasses.replace(policy, terms=tuple(self._sized(t) for t in policy.terms))
        self._check_sizes(policy)
        self.policy = policy
        joints = list(policy.joints)
        self._pos = self.state_columns("joints", [f"{j}/position" for j in joints])
        self._vel = self.state_columns("joints", [f"{j}/velocity" for j in joints])
        self._cols = self.claim("action.interface", [f"{j}/{policy.interface.value}" for j in joints])
        self._observe = Observations(policy.terms, self.nworld)
        njoint = len(joints)
        self.actions = np.zeros((self.nworld, njoint), np.float32)
        self.targets = np.zeros((self.nworld, njoint))
        self.commands = np.tile(policy.command_default, (self.nworld, 1))
        self.bad = np.zeros(self.nworld, bool)
        self._context = Context(self._pos, self._vel, policy.default, self.actions, self.commands)
        self._phase = 0  # control periods since the last inference
        self._decimation: int | None = None  # known at the first update, from its period
        self.inferences = 0

    # --- configuration ---
    def _sized(self, term: Term) -> Term:
        """A sensor term with its width, from the model's sensor of that name."""
        if term.func != "sensor":
            return term
        sensors = {s.name: s for s in self.spec.sensors}
        if term.sensor not in sensors:
            raise self.params.error(
                "observations",
                f"term {term.name!r}: the model has no sensor {term.sensor!r} (sensors: {', '.join(sensors) or 'none'})",
            )
        return dataclasses.replace(term, width=sensors[term.sensor].dim)

    def _check_sizes(self, policy: PolicySpec) -> None:
        """The model's input and output widths against the terms' and the joints'."""
        shares = ", ".join(f"{t.name} {t.size}" for t in policy.terms)
        if self.runtime.obs_size is not None and self.runtime.obs_size != policy.obs_size:
            raise self.params.error(
                "observations",
                f"the model takes {self.runtime.obs_size} observation values, the terms give {policy.obs_size} ({shares})",
            )
        if self.runtime.action_size is not None and self.runtime.action_size != len(policy.joints):
            raise self.params.error(
                "joints",
                f"the model gives {self.runtime.action_size} actions, the controller has {len(policy.joints)} joints "
                f"({', '.join(policy.joints)})",
            )

    # --- commands ---
    def set_commands(
        self, worlds: Sequence[int] | np.ndarray, rows: Sequence[Sequence[float]] | np.ndarray
    ) -> Rejections:
        """The commands of several worlds (n, ncommand); a later row for a world wins.

        Returns (index, reason) for each rejected row (a world out of range, a wrong width,
        a value not finite); those worlds keep their command. Never raises for a bad row."""
        w, rejected = self._batch_worlds(worlds)
        width = self.commands.shape[1]
        try:
            values = np.asarray(rows, dtype=np.float64).reshape(len(w), -1)
        except ValueError:
            return [(k, f"{self.name}: command must have {width} values") for k in range(len(w))]
        if values.shape[1] != width:
            return [
                (
                    k,
                    f"{self.name}: command has {values.shape[1]} values, expected {width} ({', '.join(self.policy.command_names)})",
                )
                for k in range(len(w))
            ]
        with np.errstate(invalid="ignore"):
            good = rows_all(np.isfinite(values) & (np.abs(values) < MAX_COMMAND))
        for k in np.flatnonzero(~good).tolist():
            rejected.setdefault(k, f"{self.name}: command must be finite, got {values[k].tolist()}")
        ok = np.array([k not in rejected for k in range(len(w))], bool)
        keep = np.flatnonzero(ok)
        keep = keep[last_per_world(w[keep])]
        self.commands[w[keep]] = values[keep]
        return sorted(rejected.items())

    def _twist(self, worlds: np.ndarray, rows: np.ndarray) -> Rejections:
        return self.set_commands(worlds, np.asarray(rows, np.float64)[:, _TWIST_COLUMNS])

    def topics(self) -> ControllerTopics:
        """`<ns>/<controller>/command` (Float64MultiArray, joint_position) or `<ns>/<controller>/cmd_vel` (Twist)."""
        if self.policy.command is CommandKind.VELOCITY:
            command = Input(f"{self.name}/cmd_vel", MessageKind.TWIST, self._twist)
        else:
            command = Input(
                f"{self.name}/command",
                MessageKind.FLOAT64_MULTI_ARRAY,
                self.set_commands,
                width=self.commands.shape[1],
            )
        return ControllerTopics(self.name, inputs=(command,))

    # --- the loop ---
    def activate(self, sim: Any, time: float) -> None:
        """The first period: commands given before it are kept (as every controller keeps its inputs)."""
        commands = self.commands.copy()
        self.reset(sim, np.arange(self.nworld))
        self.commands[:] = commands

    def reset(self, sim: Any, worlds: np.ndarray) -> None:
        """The listed worlds start over: no last action, the default command, fresh histories,
        and targets where the joints are now until the next inference."""
        self.actions[worlds] = 0.0
        self.commands[worlds] = self.policy.command_default
        self.bad[worlds] = False
        self._observe.reset(worlds)
        if self.policy.interface is ActionInterface.POSITION:
            self.targets[worlds] = sim.state[np.ix_(worlds, self._pos)]
        else:
            self.targets[worlds] = 0.0

    def update(self, sim: Any, time: float, period: float) -> None:
        if self._decimation is None:
            self._decimation = self._decimation_for(period)
        if self._phase % self._decimation == 0:
            self._infer(sim)
            self._phase = 0
        self._phase += 1
        sim.command[:, self._cols] = self.targets
        if self.bad.any():  # write() refuses these rows: BAD_COMMAND, their ctrl held
            sim.command[np.ix_(np.flatnonzero(self.bad), self._cols)] = np.nan

    def _decimation_for(self, period: float) -> int:
        rate = self.policy.rate
        if rate is None:
            return 1
        ratio = 1.0 / (float(rate) * period)
        decimation = max(1, round(ratio))
        if abs(ratio - decimation) > 1e-6 * ratio:
            log.warning(
                "%s: controller %r: policy_rate: %g Hz does not divide the control rate %g Hz: the policy runs every %d periods (%g Hz)",
                self.params.where,
                self.name,
                float(rate),
                1.0 / period,
                decimation,
                1.0 / (period * decimation),
            )
        return decimation

    @property
    def decimation(self) -> int | None:
        """Control periods per policy period (None before the first update)."""
        return self._decimation

    def _infer(self, sim: Any) -> None:
        obs = self._observe(sim, self._context)
        raw = np.asarray(self.runtime(obs), dtype=np.float32).reshape(self.nworld, -1)
        finite = rows_all(np.isfinite(raw))
        newly = finite.size and ~finite & ~self.bad
        if np.any(newly):
            log.warning(
                "%s: the policy gave NaN or inf actions in worlds %s: they hold their last action (BAD_COMMAND)",
                self.name,
                np.flatnonzero(newly).tolist(),
            )
        self.bad[:] = ~finite
        if self.policy.clip is not None:
            raw = np.clip(raw, *self.policy.clip)
        rows = slice(None) if finite.all() else np.flatnonzero(finite)
        self.actions[rows] = raw[rows]
        scaled = self.policy.scale * self.actions[rows]
        self.targets[rows] = (
            self.policy.default + scaled if self.policy.interface is ActionInterface.POSITION else scaled
        )
        self.inferences += 1
