"""Exploration noise on the executed actions (CGAC's action_noise), apart from the policy's entropy."""

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.noise import NormalActionNoise, VectorizedActionNoise

from sb3_cgac import CGAC
from sb3_cgac.noise import PerEnvNormalActionNoise
from sb3_cgac.vec_env import make_vec_env


def test_per_env_noise_scales():
    np.random.seed(0)
    noise = PerEnvNormalActionNoise(n_envs=64, action_dim=3, std_min=0.1, std_max=0.4)
    assert ((noise.stds >= 0.1) & (noise.stds <= 0.4)).all() and noise.stds.std() > 0.05
    samples = np.stack([noise() for _ in range(2000)])  # (draws, envs, action_dim)
    assert samples.dtype == np.float32
    np.testing.assert_allclose(samples.std(axis=(0, 2)), noise.stds[:, 0], rtol=0.1)
    before = noise.stds.copy()
    noise.reset([3, 5])  # the envs whose episode ended get new scales, the others keep theirs
    changed = np.flatnonzero(noise.stds[:, 0] != before[:, 0])
    assert changed.tolist() == [3, 5]
    with pytest.raises(ValueError, match="std_min <= std_max"):
        PerEnvNormalActionNoise(4, 1, 0.5, 0.1)


@pytest.mark.parametrize("noise_class", ["per_env", "sb3"])
def test_run_with_action_noise(noise_class):
    env = make_vec_env("Pendulum-v1", n_envs=8, seed=0)
    noise = PerEnvNormalActionNoise(8, 1, 0.2, 0.5) if noise_class == "per_env" else NormalActionNoise(np.zeros(1), np.ones(1))
    model = CGAC("MlpPolicy", env, action_noise=noise, policy_kwargs=dict(net_arch=[16, 16]), seed=0)
    model.learn(8 * 40)
    if noise_class == "sb3":  # one noise per env, as SB3's off-policy algorithms make it
        assert isinstance(model.action_noise, VectorizedActionNoise) and model.action_noise.n_envs == 8
    # The window holds the executed actions: within [-1, 1], and off the averaged actor's samples
    actions = model.rollout_buffer.actions[: model.rollout_buffer.size]
    assert actions.abs().max() <= 1.0
    quiet = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=8, seed=0), policy_kwargs=dict(net_arch=[16, 16]), seed=0)
    quiet.learn(8 * 40)
    assert not th.equal(actions, quiet.rollout_buffer.actions[: quiet.rollout_buffer.size])


def test_action_noise_bad_input():
    env = make_vec_env("Pendulum-v1", n_envs=8, seed=0)
    model = CGAC("MlpPolicy", env, action_noise=PerEnvNormalActionNoise(4, 1, 0.1, 0.2), policy_kwargs=dict(net_arch=[16]))
    with pytest.raises(ValueError, match="made for 4 envs, the env has 8"):
        model.learn(64)
    torch_env = make_vec_env("Pendulum-v1", n_envs=8, seed=0, backend="gymnasium_torch")
    noise = NormalActionNoise(np.zeros(1), np.ones(1))
    model = CGAC("MlpPolicy", torch_env, action_noise=noise, policy_kwargs=dict(net_arch=[16]))
    with pytest.raises(ValueError, match="not with a torch-native env"):
        model.learn(64)


def test_zoo_per_env_noise(tmp_path):
    pytest.importorskip("rl_zoo3")
    from sb3_cgac.zoo import build_model

    hyperparams = {"noise_type": "per_env_normal", "noise_std": [0.1, 0.3]}
    model, _ = build_model("cgac", "Pendulum-v1", log_folder=str(tmp_path), hyperparams=hyperparams)
    noise = model.action_noise
    assert isinstance(noise, PerEnvNormalActionNoise) and noise.n_envs == model.n_envs and noise.action_dim == 1
    assert (noise.std_min, noise.std_max) == (0.1, 0.3)
    hyperparams["noise_std"] = 0.2
    with pytest.raises(ValueError, match="noise_std: \\[std_min, std_max\\]"):
        build_model("cgac", "Pendulum-v1", log_folder=str(tmp_path), hyperparams=hyperparams)
