"""A gymnasium `VectorEnv` over the contract: one sub-environment per world.

    env = batchsim.vector.make("arm", 64, "cpu", reward=reward, terminated=terminated,
                               max_episode_steps=500, randomize="randomize.yaml")
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())

Observations are the exported state interfaces (`sim.state`, float64, `(nworld, nstate)`);
actions are the command interfaces (`sim.command`, `(nworld, ncommand)`), bounded by the
actuators' ctrlrange where they have one. One step is `nstep` physics steps (a control period:
write, step, read, as a ros2_control loop runs). Reward and termination come from the
caller's functions of the batch; a world that diverged or overflowed is terminated (its
frozen state would teach nothing), and `max_episode_steps` truncates. Each world autoresets
on its own, in gymnasium's next-step mode (default) or same-step mode (`final_obs` in info),
or not at all (DISABLED: `reset(options={"worlds": [...]})`),
with a fresh draw of its randomized conditions where the variation says `redraw_on_reset`.
`reset(seed=s)` restarts the variation's draws from seed s, so a seeded reset repeats.

By default arrays are host NumPy arrays on every backend: the contract's read() and write()
path, one download and one upload per step. With `device=True` observations stay on the
engine's device and actions are taken there (the contract's `device_state()` and
`write_device()`): the backend's own arrays (warp: `wp.array`, mjx: `jax.Array`, float32),
DLPack-capable (`torch.from_dlpack(obs)`); only the rewards and the done flags, `(nworld,)`
each, come to the host, where the resets are decided. Next-step and disabled autoreset only
(same-step's `final_obs` would copy rows on the device), and commands that map one to one
onto actuators.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv

import batchsim
from batchsim.contract import Contract
from batchsim.model import CommandMode, InterfaceKind
from batchsim.types import FROZEN

#: reward(obs (n, nstate), action (n, ncommand), sim) -> (n,) float
Reward = Callable[[np.ndarray, np.ndarray, Contract], np.ndarray]
#: terminated(obs (n, nstate), sim) -> (n,) bool
Terminated = Callable[[np.ndarray, Contract], np.ndarray]


class BatchsimVectorEnv(VectorEnv):
    """`sim.nworld` sub-environments, one per world of a configured (or new) system.

    Args:
      sim: the worlds; configured and activated here if they are not yet.
      reward: each world's reward after a step; None: 0.
      terminated: which worlds' episodes ended after a step; None: none (beyond failed worlds).
      max_episode_steps: truncate an episode after this many steps; None: never.
      nstep: physics steps per env step (default: the model's 100 Hz control period).
      autoreset_mode: gymnasium's NEXT_STEP (default), SAME_STEP or DISABLED.
      device: observations and actions on the engine's device (see the module's docstring).
    """

    def __init__(
        self,
        sim: Contract,
        *,
        reward: Reward | None = None,
        terminated: Terminated | None = None,
        max_episode_steps: int | None = None,
        nstep: int | None = None,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        device: bool = False,
    ):
        self.sim = sim
        self.device = bool(device)
        if sim.lifecycle_state is batchsim.LifecycleState.UNCONFIGURED:
            sim.configure()
        if sim.lifecycle_state is batchsim.LifecycleState.INACTIVE:
            sim.activate()
        self.num_envs = sim.nworld
        self.nstep = int(nstep) if nstep is not None else max(1, round(0.01 / sim.dt))
        if self.nstep < 1:
            raise ValueError(f"nstep must be >= 1, got {nstep}")
        if max_episode_steps is not None and max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be >= 1, got {max_episode_steps}")
        self.max_episode_steps = max_episode_steps
        self._reward, self._terminated = reward, terminated
        self.autoreset_mode = AutoresetMode(autoreset_mode)
        if self.device and self.autoreset_mode is AutoresetMode.SAME_STEP:
            raise ValueError(
                "device=True autoresets in next-step or disabled mode (same-step's final_obs would copy on the device)"
            )
        self.metadata = {"autoreset_mode": self.autoreset_mode}
        nstate, ncommand = len(sim.export_state_interfaces()), len(sim.export_command_interfaces())
        dtype = sim.device_dtype if self.device else np.float64  # the GPU engines' float32
        self.single_observation_space = gym.spaces.Box(-np.inf, np.inf, (nstate,), dtype)
        low, high = command_bounds(sim)
        self.single_action_space = gym.spaces.Box(low, high, (ncommand,), np.float64)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, self.num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, self.num_envs)
        self._steps = np.zeros(self.num_envs, np.int64)
        self._done = np.zeros(self.num_envs, bool)  # next-step mode: the worlds to reset first

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict]:
        """Reset every world, or only those of `options`: gymnasium's `{"reset_mask": mask}` (a
        (num_envs,) bool array, as its vector envs take it) or `{"worlds": [...]}`; `seed` restarts
        the variation's draws (and the action space's sampler) from it. The observation is every
        world's."""
        super().reset(seed=seed)
        if seed is not None:
            self.sim.reseed(seed)
            self.action_space.seed(seed)
        worlds = self._worlds_of(options or {})
        self.sim.reset(worlds)
        rows = slice(None) if worlds is None else worlds
        self._steps[rows] = 0
        self._done[rows] = False
        return self._observe(), {}

    def _worlds_of(self, options: dict[str, Any]) -> np.ndarray | None:
        """The worlds a reset's options name (None: every world), checked as gymnasium checks them."""
        mask, worlds = options.get("reset_mask"), options.get("worlds")
        if mask is not None and worlds is not None:
            raise ValueError("reset options: give `reset_mask` or `worlds`, not both")
        if mask is None:
            return None if worlds is None else np.asarray(worlds)
        if not isinstance(mask, np.ndarray):
            raise TypeError(f"`options['reset_mask']` must be a numpy array, got {type(mask)}")
        if mask.shape != (self.num_envs,):
            raise ValueError(f"`options['reset_mask']` must have shape `({self.num_envs},)`, got {mask.shape}")
        if mask.dtype != np.bool_:
            raise TypeError(f"`options['reset_mask']` must have `dtype=np.bool_`, got {mask.dtype}")
        if not mask.any():
            raise ValueError("`options['reset_mask']` must contain at least one True value")
        return np.flatnonzero(mask)

    def _observe(self) -> Any:
        return self.sim.device_state() if self.device else self.sim.state.copy()

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
        sim = self.sim
        if not self.device:
            actions = np.asarray(actions, np.float64)
        shape = tuple(getattr(actions, "shape", ()))
        if shape != self.action_space.shape:
            raise ValueError(f"actions must have shape {self.action_space.shape}, got {shape}")
        restart = np.flatnonzero(self._done)  # next-step mode: worlds whose episode ended last step
        if self.device:
            sim.write_device(actions)
        else:
            sim.command[:] = actions
            sim.write()
        sim.step(self.nstep)
        if not self.device:
            sim.read()
        if restart.size:  # their step is their reset: its observation, no reward, not done
            sim.reset(restart)
        obs = self._observe()
        self._steps += 1
        self._steps[restart] = 0
        reward = (
            np.zeros(self.num_envs)
            if self._reward is None
            else _host(self._reward(obs, actions, sim), np.float64)
        )
        ended = (sim.status & np.uint8(FROZEN)) != 0
        if self._terminated is not None:
            ended |= _host(self._terminated(obs, sim), bool)
        truncated = np.zeros(self.num_envs, bool)
        if self.max_episode_steps is not None:
            truncated = (self._steps >= self.max_episode_steps) & ~ended
        reward[restart], ended[restart], truncated[restart] = 0.0, False, False
        done = ended | truncated
        info: dict[str, Any] = {}
        if self.autoreset_mode is AutoresetMode.NEXT_STEP:
            self._done = done
        elif self.autoreset_mode is AutoresetMode.SAME_STEP and done.any():
            worlds = np.flatnonzero(done)
            info = {"final_obs": obs.copy(), "_final_obs": done.copy()}
            sim.reset(worlds)
            self._steps[worlds] = 0
            obs[worlds] = sim.state[worlds]
        return obs, reward, ended, truncated, info

    def close_extras(self, **kwargs: Any) -> None:
        if self.sim.lifecycle_state is not batchsim.LifecycleState.FINALIZED:
            self.sim.shutdown()


class WorldEnv(gym.Env):
    """One world as a gymnasium `Env` (gymnasium's `check_env` runs on it; a SyncVectorEnv of
    them is the reference the vector env is tested against): BatchsimVectorEnv's arguments,
    over a system of one world (`world_offset=i` draws as world i of a fleet)."""

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(self, sim: Contract, **env_options: Any):
        if sim.nworld != 1:
            raise ValueError(f"a WorldEnv is one world; this system has {sim.nworld}")
        self._vector = BatchsimVectorEnv(sim, autoreset_mode=AutoresetMode.DISABLED, **env_options)
        self.observation_space = self._vector.single_observation_space
        self.action_space = self._vector.single_action_space

    @property
    def sim(self) -> Contract:
        return self._vector.sim

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        if seed is not None:
            self.action_space.seed(seed)
        obs, info = self._vector.reset(seed=seed, options=options)
        return obs[0], info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        obs, reward, terminated, truncated, info = self._vector.step(np.asarray(action, np.float64)[None])
        return obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), info

    def close(self) -> None:
        self._vector.close()


def _host(values: Any, dtype: Any) -> np.ndarray:
    """A callable's (nworld,) result on the host, whatever array it is (a wp.array: .numpy())."""
    if hasattr(values, "numpy") and not isinstance(values, np.ndarray):
        values = values.numpy()
    return np.array(values, dtype=dtype)


def command_bounds(sim: Contract) -> tuple[np.ndarray, np.ndarray]:
    """(ncommand,) low and high of each command interface: the actuator's ctrlrange (through the
    interface's scale and offset) where it is limited, else a position interface's joint range
    (ros2_control's position limits) where the joint is limited; else infinite."""
    m = sim.model
    low, high = np.full(len(sim.spec.commands), -np.inf), np.full(len(sim.spec.commands), np.inf)
    for c, cmd in enumerate(sim.spec.commands):
        a = cmd.actuator_id
        if cmd.mode is CommandMode.DIRECT and a >= 0 and m.actuator_ctrllimited[a] and cmd.scale:
            ends = (m.actuator_ctrlrange[a] - cmd.offset) / cmd.scale
            low[c], high[c] = ends.min(), ends.max()
        elif cmd.kind is InterfaceKind.POSITION and cmd.joint is not None:
            j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, cmd.joint)
            if j >= 0 and m.jnt_limited[j]:
                low[c], high[c] = m.jnt_range[j]
    return low, high


def make(
    model: Any,
    nworld: int,
    backend: str = "auto",
    *,
    reward: Reward | None = None,
    terminated: Terminated | None = None,
    max_episode_steps: int | None = None,
    nstep: int | None = None,
    autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
    device: bool = False,
    **make_options: Any,
) -> BatchsimVectorEnv:
    """A vector env of `nworld` worlds of `model` on `backend`: batchsim.make's arguments
    (`randomize=`, `world_offset=`, backend options) and BatchsimVectorEnv's."""
    sim = batchsim.make(model, nworld, backend, **make_options)
    return BatchsimVectorEnv(
        sim,
        reward=reward,
        terminated=terminated,
        max_episode_steps=max_episode_steps,
        nstep=nstep,
        autoreset_mode=autoreset_mode,
        device=device,
    )
