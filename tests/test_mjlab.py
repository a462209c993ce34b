"""mjlab (MuJoCo Warp on its CPU backend here) through MjlabVectorEnv and TorchVecEnv: the episode contract checked
against the task driven directly, and CGAC trained on it. mjlab pins its own mujoco and rsl-rl-lib, so it has its own
environment: the README's mjlab command (CI sets SB3_CGAC_REQUIRE_MJLAB=1 there, so that a failed install fails)."""

import os

import pytest

if os.environ.get("SB3_CGAC_REQUIRE_MJLAB") != "1":
    pytest.importorskip("mjlab")

import numpy as np
import torch as th
from mjlab.envs import ManagerBasedRlEnv
from mjlab.tasks.registry import load_env_cfg

from sb3_cgac import CGAC
from sb3_cgac.vec_env import TorchVecEnv, make_vec_env
from sb3_cgac.vec_env.mjlab_vec_env import MjlabVectorEnv

TASK = "Mjlab-Cartpole-Balance"  # no contacts, 0.05 s per step, time-outs only
EPISODE = 12
LIMIT_S = (EPISODE - 0.5) * 0.05  # mjlab rounds the time limit up to whole steps


def test_steps_match_the_task_driven_directly():
    n_envs, seed = 3, 7
    env = MjlabVectorEnv(TASK, n_envs, device="cpu", episode_length_s=LIMIT_S)
    assert env.max_episode_steps == EPISODE and set(env.single_observation_space.spaces) == {"actor", "critic"}
    # The same task with a later time limit and no reset: its observation at step EPISODE is the real last one
    cfg = load_env_cfg(TASK)
    cfg.scene.num_envs, cfg.auto_reset, cfg.episode_length_s = n_envs, False, LIMIT_S + 0.3
    reference = ManagerBasedRlEnv(cfg, device="cpu")

    obs, _ = env.reset(seed=seed)
    expected, _ = reference.reset(seed=seed)
    for key in obs:
        th.testing.assert_close(obs[key], expected[key])
    rng = np.random.default_rng(0)
    for t in range(1, EPISODE + 3):
        actions = th.as_tensor(rng.uniform(-1, 1, (n_envs, 1)), dtype=th.float32)
        obs, rewards, terminated, truncated, info = env.step(actions)
        assert obs["actor"].dtype == th.float32 and terminated.dtype == th.bool and truncated.dtype == th.bool
        assert not terminated.any()  # the balance task only times out
        if t <= EPISODE:
            expected, expected_rewards, _, _, _ = reference.step(actions)
            th.testing.assert_close(rewards, expected_rewards)
            last = info["final_obs"] if t == EPISODE else obs
            for key in obs:
                th.testing.assert_close(last[key], expected[key])
            assert bool(truncated.all()) == bool(truncated.any()) == (t == EPISODE)
            if t == EPISODE:  # the envs were reset to new first states
                assert not th.allclose(obs["critic"], expected["critic"])
        else:
            assert not truncated.any()  # a new episode


def test_partial_reset_and_random_first_episode():
    env = make_vec_env(TASK, 8, backend="mjlab", seed=0, vec_env_kwargs=dict(device="cpu", episode_length_s=LIMIT_S))
    assert isinstance(env, TorchVecEnv) and env.max_episode_steps() == EPISODE
    env.reset()
    ends = th.zeros(8, dtype=th.int64)
    for _ in range(EPISODE):
        ends += env.step_tensors(th.zeros(8, 1)).truncated.long()
    # Every env's first episode ends once within its time limit (a random cut, or the limit itself); only the
    # episodes that reached the limit are reported, as Monitor would
    assert (ends == 1).all()
    for _ in range(EPISODE):  # every env's second episode reaches the time limit
        env.step_tensors(th.zeros(8, 1))
    episodes = env.pop_episodes()
    assert len(episodes) >= 8 and all(episode["l"] == EPISODE for episode in episodes)
    # Each reward term of the task reaches the episode statistics; their means add up to the mean return
    terms = [f"reward_{term}" for term in load_env_cfg(TASK).rewards]
    assert terms and all(set(terms) <= set(episode) for episode in episodes)
    mean_terms = sum(np.mean([episode[key] for episode in episodes]) for key in terms)
    np.testing.assert_allclose(mean_terms, np.mean([episode["r"] for episode in episodes]), rtol=1e-4)


def test_cgac_trains_on_mjlab(tmp_path):
    kwargs = dict(device="cpu", episode_length_s=LIMIT_S)
    env = make_vec_env(TASK, 8, backend="mjlab", seed=0, vec_env_kwargs=kwargs)
    policy_kwargs = dict(net_arch=[32, 32], actor_keys=["actor"], critic_keys=["critic"])
    model = CGAC("MultiInputPolicy", env, batch_size=64, buffer_window=8, policy_kwargs=policy_kwargs, seed=0)
    model.learn(8 * 40)
    assert model.num_timesteps == 8 * 40 and model.rollout_buffer.truncated.any()
    assert [episode["l"] for episode in model.ep_info_buffer] and all(e["l"] == EPISODE for e in model.ep_info_buffer)
    model.save(tmp_path / "model")
    loaded = CGAC.load(tmp_path / "model")
    obs = env.reset()
    actor_obs = {"actor": obs["actor"]}  # predict() needs only the actor's keys
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(actor_obs, deterministic=True)[0])


def test_unknown_task():
    with pytest.raises(ValueError, match="mjlab has no task 'NoSuchTask'"):
        MjlabVectorEnv("NoSuchTask", 2, device="cpu")
