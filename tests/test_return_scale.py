"""gamma='auto' (the discount from the time limit) and scale_rewards (the rewards divided by the returns' spread)."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_cgac import CGAC
from sb3_cgac.hyperparameters import episode_horizon, horizon_gamma
from sb3_cgac.return_scale import RETURN_LIMIT, ReturnScale

SMALL = dict(policy_kwargs=dict(net_arch=[16, 16]), seed=0)


def test_horizon_gamma_follows_td_mpc2():
    assert horizon_gamma(200) == pytest.approx(0.975)
    assert horizon_gamma(1000) == horizon_gamma(5000) == pytest.approx(0.995)
    assert horizon_gamma(150) == pytest.approx(29 / 30) and horizon_gamma(10) == 0.95
    assert horizon_gamma(None) == 0.99


def test_gamma_auto_reads_the_time_limit():
    assert CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4), gamma="auto", **SMALL).gamma == pytest.approx(0.975)
    # A time limit set at make time, and an env without one
    env = make_vec_env("Pendulum-v1", n_envs=4, env_kwargs=dict(max_episode_steps=1000))
    assert episode_horizon(env) == 1000
    unlimited = make_vec_env(lambda: gym.make("Pendulum-v1", max_episode_steps=None).unwrapped, n_envs=2)
    assert episode_horizon(unlimited) is None
    assert CGAC("MlpPolicy", unlimited, gamma="auto", **SMALL).gamma == 0.99


def test_gamma_auto_is_saved_resolved(tmp_path):
    model = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4), gamma="auto", **SMALL)
    model.save(tmp_path / "model")
    assert CGAC.load(tmp_path / "model").gamma == pytest.approx(0.975)


def test_gamma_must_be_a_number_or_auto():
    with pytest.raises(ValueError, match="gamma must be a number in \\[0, 1\\] or 'auto'"):
        CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4), gamma="horizon", **SMALL)


def discounted_returns(rewards: np.ndarray, dones: np.ndarray, gamma: float) -> np.ndarray:
    returns, running = np.zeros_like(rewards), np.zeros(rewards.shape[1])
    for t in range(len(rewards)):
        running = gamma * running + rewards[t]
        returns[t] = running
        running = np.where(dones[t], 0.0, running)
    return returns


def test_return_scale_matches_numpy():
    rng = np.random.default_rng(0)
    rewards = rng.normal(3.0, 2.0, (300, 8))
    dones = rng.random((300, 8)) < 0.02
    scale = ReturnScale(gamma=0.9)
    steps = zip(rewards, dones, strict=True)
    scaled = [scale.scale_rewards(th.as_tensor(r, dtype=th.float32), th.as_tensor(d)) for r, d in steps]
    returns = discounted_returns(rewards, dones, 0.9)
    expected = max(returns.std(), np.abs(returns).max() / RETURN_LIMIT)
    assert float(scale.scale()) == pytest.approx(expected, rel=1e-5)
    np.testing.assert_allclose(scaled[-1].numpy(), rewards[-1] / expected, rtol=1e-5)


def test_a_sparse_reward_stays_within_the_limit():
    # Zeros, then a first reward of 100: the statistics take it in before it is scaled
    scale = ReturnScale(gamma=0.99)
    for _ in range(50):
        assert th.equal(scale.scale_rewards(th.zeros(4), th.zeros(4, dtype=th.bool)), th.zeros(4))
    first = scale.scale_rewards(th.tensor([100.0, 0.0, 0.0, 0.0]), th.zeros(4, dtype=th.bool))
    assert 0 < float(first[0]) <= RETURN_LIMIT
    # Non-finite rewards pass through (the window excludes them) and stay out of the statistics
    before = float(scale.scale())
    out = scale.scale_rewards(th.tensor([float("nan"), 0.0, 0.0, 0.0]), th.zeros(4, dtype=th.bool))
    assert th.isnan(out[0]) and float(scale.scale()) == pytest.approx(before, rel=0.2)


def test_scale_rewards_trains_saves_and_loads(tmp_path):
    env = make_vec_env("Pendulum-v1", n_envs=8, seed=0)
    model = CGAC("MlpPolicy", env, scale_rewards=True, batch_size=64, **SMALL)
    model.learn(8 * 64)
    scale = float(model.return_scale.scale())
    # Pendulum's rewards lie in [-16.3, 0] (an untrained policy's mostly below -1): the window holds them scaled
    # (each by the scale of its step), the logger the scale
    assert scale > 10 and model.logger.name_to_value["train/reward_scale"] == pytest.approx(scale, rel=0.1)
    stored = model.rollout_buffer.rewards[: model.rollout_buffer.size]
    assert float(stored.max()) <= 0 and float(stored.min()) > -1
    model.save(tmp_path / "model")
    loaded = CGAC.load(tmp_path / "model", env=env)
    assert loaded.scale_rewards and float(loaded.return_scale.scale()) == pytest.approx(scale)
    count = float(loaded.return_scale.statistics.count)
    loaded.learn(8 * 8, reset_num_timesteps=False)
    assert float(loaded.return_scale.statistics.count) == count + 8 * 8
