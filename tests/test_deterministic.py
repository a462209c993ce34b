import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_cgac import CGAC


@pytest.mark.parametrize("kwargs", [{}, dict(n_steps=8, buffer_window=8, ent_coef="auto", predict_tau=0.01)])
def test_deterministic_training(kwargs):
    """Two runs with the same seed give identical parameters and actions (on CPU)."""
    results = []
    for _ in range(2):
        env = make_vec_env("Pendulum-v1", n_envs=4)
        model = CGAC("MlpPolicy", env, seed=1, policy_kwargs=dict(net_arch=[16, 16]), device="cpu", **kwargs)
        model.learn(400)
        obs = np.linspace(-1, 1, 12, dtype=np.float32).reshape(4, 3)
        actions = [model.predict(obs, deterministic=False)[0] for _ in range(3)]
        results.append(([p.detach().clone() for p in model.policy.parameters()], actions))
    (params_a, actions_a), (params_b, actions_b) = results
    assert all(th.equal(a, b) for a, b in zip(params_a, params_b, strict=True))
    assert all(np.array_equal(a, b) for a, b in zip(actions_a, actions_b, strict=True))


def test_different_seeds_differ():
    params = []
    for seed in (1, 2):
        model = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4), seed=seed, policy_kwargs=dict(net_arch=[16]))
        model.learn(200)
        params.append(model.actor.mu.weight.detach().clone())
    assert not th.equal(params[0], params[1])
