"""Train arm_reach.onnx: the batchsim arm reaching a commanded joint target, with PPO from
stable-baselines3 on batchsim's own worlds, randomized as randomize.yaml says.

    pip install -e '.[policy,train]'
    python examples/policies/train_arm_reach.py            # ~5 minutes on 2 cores
    batchsim evaluate --model arm --controllers examples/policies/arm_reach.yaml \
        --randomize examples/policies/randomize.yaml --worlds 64

It trains for the controller block of arm_reach.yaml, read with batchsim's own reader: the
same joints, observation terms (built by the PolicyController's own Observations), action
scale and clip, policy rate and command ranges, so what is trained is what the controller runs.
Each world is an environment; an episode is 2 s with a target drawn as `batchsim evaluate`
draws them, and a fresh draw of masses, friction, damping and servo gains. The trained actor
(deterministic: the mean) is written to ONNX with mjlab's metadata keys.
"""

from __future__ import annotations

import argparse
import datetime
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecEnv

import batchsim
from batchsim.controllers.policy import Context, Observations
from batchsim.controllers.policy.export import export_mlp
from batchsim.evaluation.commands import draw_commands
from batchsim.evaluation.policy_file import read_policy_yaml

HERE = Path(__file__).resolve().parent


class ArmReach(VecEnv):
    """`nworld` arms as a stable-baselines3 VecEnv, one policy step per `step`."""

    def __init__(self, nworld: int, yaml: Path, randomize: Path, seed: int, episode_seconds: float = 2.0):
        _, self.spec = read_policy_yaml(yaml)
        spec = self.spec
        self.sim = sim = batchsim.make("arm", nworld, "cpu", randomize=str(randomize), nthread=1)
        sim.configure()
        sim.activate()
        sim.reseed(seed)
        names, commands = sim.export_state_interfaces(), sim.export_command_interfaces()
        self.pos = np.array([names.index(f"{j}/position") for j in spec.joints])
        self.vel = np.array([names.index(f"{j}/velocity") for j in spec.joints])
        self.cols = np.array([commands.index(f"{j}/{spec.interface.value}") for j in spec.joints])
        self.nstep = round(1.0 / (spec.rate * sim.dt))  # physics steps per policy step
        self.horizon = round(episode_seconds * spec.rate)
        self.seed_ = seed
        njoint = len(spec.joints)
        self.actions = np.zeros((nworld, njoint), np.float32)
        self.commands = np.zeros((nworld, njoint))
        self.episode = np.zeros(nworld, np.int64)
        self.t = np.zeros(nworld, np.int64)
        self.observe = Observations(spec.terms, nworld)
        self.context = Context(self.pos, self.vel, spec.default, self.actions, self.commands)
        lo, hi = spec.clip
        super().__init__(
            nworld,
            gym.spaces.Box(-np.inf, np.inf, (spec.obs_size,), np.float32),
            gym.spaces.Box(lo, hi, (njoint,), np.float32),
        )
        self._pending = None

    def _start(self, worlds: np.ndarray) -> None:
        """The listed worlds begin an episode: a fresh draw (reset), a new target."""
        if len(worlds) < self.num_envs or self.episode.any():
            self.sim.reset(worlds)  # redraws the conditions (redraw_on_reset)
        self.sim.read()
        # a training-only seed offset: the targets trained on are not the ones evaluated with seed 0
        self.commands[worlds] = draw_commands(
            self.spec.command_ranges, self.seed_ + 1000, worlds, self.episode[worlds]
        )
        self.actions[worlds] = 0.0
        self.observe.reset(worlds)
        self.t[worlds] = 0

    def reset(self) -> np.ndarray:
        self._start(np.arange(self.num_envs))
        return self.observe(self.sim, self.context)

    def step_async(self, actions: np.ndarray) -> None:
        self._pending = np.clip(actions, *self.spec.clip).astype(np.float32)

    def step_wait(self):
        sim, spec, a = self.sim, self.spec, self._pending
        change = np.square(a - self.actions).sum(axis=1)
        self.actions[:] = a
        sim.command[:, self.cols] = spec.default + spec.scale * a
        sim.write()
        sim.step(self.nstep)
        sim.read()
        self.t += 1
        err = np.abs(sim.state[:, self.pos] - self.commands)
        reward = -err.mean(axis=1) + 0.5 * (err.max(axis=1) < 0.05) - 0.005 * change
        obs = self.observe(sim, self.context)
        done = self.t >= self.horizon
        infos = [{} for _ in range(self.num_envs)]
        ended = np.flatnonzero(done)
        if ended.size:
            for w in ended:
                infos[w]["terminal_observation"] = obs[w].copy()
                infos[w]["TimeLimit.truncated"] = True
            self.episode[ended] += 1
            self._start(ended)
            obs[ended] = self.observe(sim, self.context)[ended]
        return obs, reward.astype(np.float32), done, infos

    # the VecEnv methods a PPO run does not call
    def close(self) -> None:
        pass

    def get_attr(self, attr_name, indices=None):
        return [getattr(self, attr_name)] * self.num_envs

    def set_attr(self, attr_name, value, indices=None):
        setattr(self, attr_name, value)

    def env_method(self, method_name, *args, indices=None, **kwargs):
        return [None] * self.num_envs

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False] * self.num_envs


def export(model: PPO, env: ArmReach, path: Path, steps: int, seed: int) -> Path:
    """The actor's mean (policy MLP, then the action head) to ONNX, with mjlab's metadata."""
    policy = model.policy
    linears = [m for m in policy.mlp_extractor.policy_net if hasattr(m, "weight")] + [policy.action_net]
    layers = [(m.weight.detach().cpu().numpy().T, m.bias.detach().cpu().numpy()) for m in linears]
    spec = env.spec
    metadata = {
        "joint_names": ",".join(spec.joints),
        "default_joint_pos": ",".join(f"{v:g}" for v in spec.default),
        "action_scale": ",".join(f"{v:g}" for v in spec.scale),
        "observation_names": ",".join(t.name for t in spec.terms),
        "command_names": ",".join(spec.command_names),
        "trained_with": f"stable-baselines3 PPO, {steps} steps, seed {seed}, batchsim examples/policies/train_arm_reach.py, "
        f"{datetime.date.today().isoformat()}",
    }
    return export_mlp(path, layers, "tanh", metadata)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", type=int, default=64)
    parser.add_argument(
        "--steps", type=int, default=1_500_000, help="environment steps in all (worlds x policy steps)"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=HERE / "arm_reach.onnx")
    parser.add_argument("--controllers", type=Path, default=HERE / "arm_reach.yaml")
    parser.add_argument("--randomize", type=Path, default=HERE / "randomize.yaml")
    args = parser.parse_args(argv)
    torch.set_num_threads(
        1
    )  # a 64x64 network: threads cost more than they give, and the physics has the other core
    env = ArmReach(args.worlds, args.controllers, args.randomize, args.seed)
    model = PPO(
        "MlpPolicy",
        env,
        n_steps=64,
        batch_size=1024,
        n_epochs=8,
        learning_rate=3e-4,
        gamma=0.98,
        gae_lambda=0.95,
        policy_kwargs={"net_arch": [64, 64], "log_std_init": -1.0},
        seed=args.seed,
        device="cpu",
        verbose=0,
    )
    start = time.perf_counter()
    model.learn(total_timesteps=args.steps)
    print(f"trained {args.steps} steps on {args.worlds} worlds in {time.perf_counter() - start:.0f} s")
    print(f"wrote {export(model, env, args.out, args.steps, args.seed)}")


if __name__ == "__main__":
    main()
