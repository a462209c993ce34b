"""rsl_rl's PPO on SB3 vector envs (sb3_cgac.rsl_rl): the adapter, the SB3 interface, and rsl_rl's own runner."""

import numpy as np
import pytest
import torch as th

pytest.importorskip("rsl_rl")

from rsl_rl.runners import OnPolicyRunner
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import VecNormalize
from toy_envs import PrivilegedEnv

from sb3_cgac.rsl_rl import RslPPO, RslRlVecEnv

SMALL = dict(hidden_dims=[16, 16], obs_normalization=True)


def test_run_box_and_dict():
    model = RslPPO("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4, seed=0), num_steps_per_env=8, policy_kwargs=SMALL)
    model.learn(4 * 8 * 3)
    assert model.num_timesteps == 96 and model._n_updates == 3 * 5 * 4
    model = RslPPO("MultiInputPolicy", make_vec_env(PrivilegedEnv, n_envs=4, seed=0), num_steps_per_env=8, policy_kwargs=SMALL)
    model.learn(64)
    mean, _ = evaluate_policy(model, model.get_env(), n_eval_episodes=2)
    assert np.isfinite(mean)


def test_asymmetric_keys():
    """The actor reads only ``actor_keys`` (predict needs only those), the critic ``critic_keys``."""
    env = make_vec_env(PrivilegedEnv, n_envs=4, seed=0)
    model = RslPPO("MultiInputPolicy", env, actor_keys=["state"], critic_keys=["privileged_state"], policy_kwargs=SMALL)
    model.learn(4 * 24)
    assert model.alg.actor.obs_groups == ["state"] and model.alg.critic.obs_groups == ["privileged_state"]
    assert model.alg.actor.mlp[0].in_features == 2 and model.alg.critic.mlp[0].in_features == 3
    obs = {"state": np.ones((3, 2), np.float32), "privileged_state": np.zeros((3, 3), np.float32)}
    changed = {**obs, "privileged_state": obs["privileged_state"] + 5}
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], model.predict(changed, deterministic=True)[0])
    with pytest.raises(ValueError, match=r"actor_keys \['velocity'\] are not keys"):
        RslPPO("MultiInputPolicy", env, actor_keys=["velocity"])
    with pytest.raises(ValueError, match="unknown policy_kwargs"):
        RslPPO("MultiInputPolicy", env, policy_kwargs=dict(net_arch=[64]))


def test_adapter_episode_contract():
    """Time limits become rsl_rl's ``time_outs``; actions are clipped to the action space; episodes reach the log."""
    venv = make_vec_env("Pendulum-v1", n_envs=3, seed=0)
    env = RslRlVecEnv(venv)
    obs = env.reset()
    assert obs["policy"].shape == (3, 3) and env.num_actions == 1
    for step in range(1, 201):
        obs, _, dones, extras = env.step(th.full((3, 1), 10.0))  # clipped to 2
        assert env.last_infos is not None
        if step < 200:
            assert not dones.any() and not extras["time_outs"].any()
    assert dones.all() and extras["time_outs"].all()
    assert "/episode_return" in extras["log"]
    # The adapter's return matches a plain run with the clipped action
    reference = make_vec_env("Pendulum-v1", n_envs=3, seed=0)
    reference.reset()
    total = sum(reference.step(np.full((3, 1), 2.0, np.float32))[1] for _ in range(200))
    assert extras["log"]["/episode_return"] == pytest.approx(float(np.mean(total)), rel=1e-5)


def test_save_load_and_deterministic(tmp_path):
    env = VecNormalize(make_vec_env("Pendulum-v1", n_envs=4, seed=0), norm_reward=False)
    model = RslPPO("MlpPolicy", env, num_steps_per_env=8, policy_kwargs=SMALL, seed=0)
    model.learn(4 * 8 * 2)
    model.save(tmp_path / "model")
    loaded = RslPPO.load(tmp_path / "model", env=env)
    obs = env.reset()
    actions = model.predict(obs, deterministic=True)[0]
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], actions)
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], actions)
    # The normaliser's statistics travelled too
    th.testing.assert_close(loaded.alg.actor.obs_normalizer._mean, model.alg.actor.obs_normalizer._mean)
    loaded.learn(64, reset_num_timesteps=False)
    assert loaded.num_timesteps == model.num_timesteps + 64


def test_same_training_as_rsl_rl_runner():
    """RslPPO's loop is rsl_rl's: the same seed trains the same parameters as rsl_rl's OnPolicyRunner on the adapter."""
    model = RslPPO(
        "MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4, seed=0), num_steps_per_env=8, policy_kwargs=SMALL, seed=3
    )
    config = model._train_config()
    initial = [value.clone() for value in model.alg.actor.state_dict().values()]
    model.learn(4 * 8 * 3)
    trained = model.alg.actor.state_dict().values()
    assert any(not th.equal(before, after) for before, after in zip(initial, trained, strict=True))

    th.manual_seed(3)
    env = RslRlVecEnv(make_vec_env("Pendulum-v1", n_envs=4, seed=3))
    env.reset()
    runner = OnPolicyRunner(env, {**config, "save_interval": 10**9}, log_dir=None)
    runner.learn(3)
    for ours, theirs in zip(model.alg.actor.state_dict().values(), runner.alg.actor.state_dict().values(), strict=True):
        th.testing.assert_close(ours, theirs, rtol=0, atol=0)
    for ours, theirs in zip(model.alg.critic.state_dict().values(), runner.alg.critic.state_dict().values(), strict=True):
        th.testing.assert_close(ours, theirs, rtol=0, atol=0)
