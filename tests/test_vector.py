"""The gymnasium vector env over the contract (issue 26): batchsim/vector.py.

gymnasium's own checker passes on one world; the vector env steps, rewards, terminates and
autoresets world for world as gymnasium's SyncVectorEnv over single worlds does (its reference
implementation), randomized worlds included; a seeded reset repeats.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import need

gym = need("gymnasium", "pip install -e '.[gym]'")
from gymnasium.utils.env_checker import check_env  # noqa: E402
from gymnasium.vector import AutoresetMode, SyncVectorEnv  # noqa: E402

import batchsim  # noqa: E402
from batchsim import vector  # noqa: E402

VARIATION = {
    "seed": 2,
    "redraw_on_reset": True,
    "fields": [{"field": "body_mass", "also": ["body_inertia"], "scale": {"uniform": [0.5, 2.0]}}],
    "start_pose": {"add": {"uniform": [-0.3, 0.3]}},
}
NWORLD = 4


def reward(obs: np.ndarray, action: np.ndarray, sim: batchsim.BatchedSystem) -> np.ndarray:
    return -np.abs(obs[:, 0] - action[:, 0])


def terminated(obs: np.ndarray, sim: batchsim.BatchedSystem) -> np.ndarray:
    return obs[:, 0] > 0.25  # joint1 swung past 0.25 rad: episodes of different lengths


OPTIONS = {"reward": reward, "terminated": terminated, "max_episode_steps": 7}


def _world(i: int, **kw) -> vector.WorldEnv:
    return vector.WorldEnv(batchsim.make("arm", 1, "cpu", randomize=VARIATION, world_offset=i), **OPTIONS, **kw)


def test_one_world_passes_gymnasiums_checker():
    env = _world(3)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_render_check=True)
    # its warnings are failures too, but two: the advice to normalize actions (commands are in
    # joint units, as ros2_control's), and unbounded observations (velocities, efforts), which
    # gymnasium's own MuJoCo envs (Ant-v5) draw as well
    allowed = ("we recommend using a symmetric and normalized space", "A Box observation space m")
    assert [str(w.message) for w in caught if not any(a in str(w.message) for a in allowed)] == []
    assert env.action_space.is_bounded()  # the arm's joint ranges bound its position commands


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_the_vector_env_is_gymnasiums_sync_env_of_single_worlds(mode):
    env = vector.make("arm", NWORLD, "cpu", randomize=VARIATION, autoreset_mode=mode, **OPTIONS)
    reference = SyncVectorEnv([lambda i=i: _world(i) for i in range(NWORLD)], autoreset_mode=mode)
    assert env.observation_space == reference.observation_space and env.action_space == reference.action_space
    obs, _ = env.reset()
    ref_obs, _ = reference.reset()
    np.testing.assert_allclose(obs, ref_obs, atol=1e-12)
    rng = np.random.default_rng(0)
    ends = 0
    for _ in range(30):
        action = np.clip(rng.normal(0.4, 0.3, env.action_space.shape), env.action_space.low, env.action_space.high)
        got = env.step(action)
        want = reference.step(action)
        for a, b in zip(got[:4], want[:4], strict=True):
            np.testing.assert_allclose(a, b, atol=1e-9)
        if mode is AutoresetMode.SAME_STEP and want[4]:
            np.testing.assert_array_equal(got[4]["_final_obs"], want[4]["_final_obs"])
            np.testing.assert_allclose(got[4]["final_obs"][got[4]["_final_obs"]], np.stack(want[4]["final_obs"][want[4]["_final_obs"]]), atol=1e-9)
        ends += int((got[2] | got[3]).sum())
    assert ends >= NWORLD  # worlds ended, at different steps, and came back with fresh draws
    assert len(set(env.sim.draw_numbers())) > 1


def test_a_seeded_reset_repeats_and_another_seed_differs():
    env = vector.make("arm", NWORLD, "cpu", randomize=VARIATION, **OPTIONS)
    first, _ = env.reset(seed=7)
    masses = env.sim.world_params()["body_mass"]
    env.step(env.action_space.sample())
    again, _ = env.reset(seed=7)
    np.testing.assert_array_equal(again, first)
    np.testing.assert_array_equal(env.sim.world_params()["body_mass"], masses)
    other, _ = env.reset(seed=8)
    assert not np.allclose(other, first)


def test_reset_mask_resets_only_the_masked_worlds_as_gymnasium_takes_it():
    """gymnasium's partial reset, `reset(options={"reset_mask": mask})`, reset every world before
    (issue 46): now only the masked ones, checked as gymnasium's vector envs check the mask."""
    env = vector.make("arm", NWORLD, "cpu", **OPTIONS)
    start, _ = env.reset(seed=1)
    for _ in range(5):
        moved, *_ = env.step(np.full(env.action_space.shape, 0.2))
    assert not np.allclose(moved, start)
    mask = np.array([False, True, False, True])
    obs, _ = env.reset(options={"reset_mask": mask})
    np.testing.assert_allclose(obs[mask], start[mask])
    np.testing.assert_allclose(obs[~mask], moved[~mask])
    for bad, error in ((np.zeros(NWORLD, bool), ValueError), (np.ones(3, bool), ValueError), ([True] * NWORLD, TypeError),
                       (np.ones(NWORLD, np.int64), TypeError)):  # fmt: skip
        with pytest.raises(error, match="reset_mask"):
            env.reset(options={"reset_mask": bad})
    with pytest.raises(ValueError, match="not both"):
        env.reset(options={"reset_mask": mask, "worlds": [0]})


def test_a_failed_world_is_terminated_and_comes_back():
    """A world that diverges is frozen by the contract: its episode ends (terminated), and the
    next step is its reset; the other world goes on."""
    env = vector.make("arm", 2, "cpu", max_episode_steps=100)
    start, _ = env.reset()
    action = np.zeros(env.action_space.shape)
    qpos, qvel = env.sim.qstate([1])
    env.sim.set_qstate([1], qpos, np.full_like(qvel, 1e11))  # beyond MuJoCo's mjMAXVAL: it diverges
    _, _, term, trunc, _ = env.step(action)
    assert list(term) == [False, True] and not trunc.any()
    obs, reward, term, trunc, _ = env.step(action)
    np.testing.assert_allclose(obs[1], start[1])  # its reset: the start again, not frozen
    assert not term.any() and reward[1] == 0 and env.sim.status[1] == 0
    with pytest.raises(ValueError, match=r"actions must have shape \(2, 6\), got \(6,\)"):
        env.step(action[0])


@pytest.mark.parametrize("backend", ["mjx", "warp"])
def test_the_device_backends_run_the_vector_env(backend):
    env = vector.make("arm", NWORLD, backend, randomize=VARIATION, **OPTIONS)
    reference = vector.make("arm", NWORLD, "cpu", randomize=VARIATION, **OPTIONS)
    obs, _ = env.reset(seed=1)
    ref, _ = reference.reset(seed=1)
    assert env.observation_space.contains(obs)
    positions = slice(0, 18, 3)
    np.testing.assert_allclose(obs[:, positions], ref[:, positions], atol=1e-6)
    action = np.full(env.action_space.shape, 0.2)
    for _ in range(5):
        obs, rew, term, trunc, _ = env.step(action)
        ref, ref_rew, *_ = reference.step(action)
    np.testing.assert_allclose(obs[:, positions], ref[:, positions], atol=1e-3)
    assert isinstance(env, gym.vector.VectorEnv) and rew.shape == (NWORLD,)
    env.close()


def _host(x):
    return x.numpy() if hasattr(x, "numpy") and not isinstance(x, np.ndarray) else np.asarray(x)


@pytest.mark.parametrize("backend", ["mjx", "warp"])
def test_the_device_path_is_the_host_path_without_the_copies(backend):
    """device=True: observations are the backend's own device arrays and actions go in as
    device arrays (device_state, write_device); the episodes are the host path's, bit for bit."""

    def device_reward(obs, action, sim):
        return -((_host(obs)[:, 0] - _host(action)[:, 0]) ** 2)

    def device_terminated(obs, sim):
        return _host(obs)[:, 0] > 0.25

    options = {"reward": device_reward, "terminated": device_terminated, "max_episode_steps": 7, "randomize": VARIATION}
    env = vector.make("arm", NWORLD, backend, device=True, **options)
    host = vector.make("arm", NWORLD, backend, **options)
    obs, _ = env.reset(seed=3)
    ref, _ = host.reset(seed=3)
    native = {"mjx": "ArrayImpl", "warp": "array"}[backend]  # jax.Array, wp.array: no host copy
    assert type(obs).__name__ == native and env.observation_space.dtype == np.float32
    np.testing.assert_array_equal(_host(obs), ref)
    if backend == "mjx":
        import jax.numpy as jnp

        to_device = jnp.asarray
    else:
        import warp as wp

        def to_device(a):
            return wp.array(a, dtype=wp.float32, device=env.sim.device)

    rng = np.random.default_rng(1)
    ends = 0
    for _ in range(30):
        action = rng.normal(0.4, 0.3, (NWORLD, 6)).astype(np.float32)
        obs, reward, term, trunc, _ = env.step(to_device(action))
        ref, ref_reward, ref_term, ref_trunc, _ = host.step(action.astype(np.float64))
        np.testing.assert_array_equal(_host(obs), ref)
        np.testing.assert_array_equal(term, ref_term)
        np.testing.assert_array_equal(trunc, ref_trunc)
        np.testing.assert_allclose(reward, ref_reward, atol=1e-6)
        ends += int((term | trunc).sum())
    assert ends >= NWORLD
    with pytest.raises(ValueError, match=r"command must have shape \(4, 6\), got \(6,\)"):
        env.sim.write_device(to_device(np.zeros(6, np.float32)))


def test_the_device_path_is_refused_where_commands_run_on_the_host():
    with pytest.raises(ValueError, match="next-step or disabled"):
        vector.make("arm", 2, "cpu", device=True, autoreset_mode=AutoresetMode.SAME_STEP)
    robot = Path(__file__).parent / "upstream" / "mujoco_ros2_control_demos" / "demo_resources" / "robot"
    urdf = f"{robot / 'test_robot.urdf'} use_pid:=true use_mjcf_from_topic:=true"
    env = vector.make(urdf, 2, "cpu", device=True)
    env.reset()
    with pytest.raises(batchsim.ConfigurationError, match="not plain copies into actuators"):
        env.step(np.zeros(env.action_space.shape))
