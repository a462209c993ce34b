"""
MyoSuite's muscle models, in the environment of the ``myosuite`` extra (MyoSuite 3.0.0 needs gymnasium<1.3, so it
has its own venv: the README's "High-dimensional tasks" command builds it and runs this file). Skipped elsewhere.
"""

import os

import numpy as np
import pytest
import yaml

if os.environ.get("SB3_CGAC_REQUIRE_MYOSUITE"):
    import myosuite  # noqa: F401  (CI's MyoSuite step: a MyoSuite that does not import is a failure, not a skip)
else:
    pytest.importorskip("myosuite")

import gymnasium as gym

from sb3_cgac import CGAC
from sb3_cgac.vec_env import make_vec_env

# The tasks of the hyperparameter files: 80 muscles (legs), 290 muscles (legs and torso)
MYOSUITE_TASKS = ("myoLegWalk-v0", "myoChallengeSoccerP1-v0")


@pytest.mark.parametrize("env_id", MYOSUITE_TASKS)
def test_registered_offline(env_id):
    """The tasks make and step without downloads, with the action sizes the hyperparameter entries are meant for."""
    env = gym.make(env_id)
    obs, _ = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    assert env.action_space.shape[0] >= 80
    env.step(env.action_space.sample())
    env.close()


def test_run_save_load(tmp_path):
    """CGAC trains a few hundred steps on the 80-muscle leg, then saves, loads and predicts the same actions."""
    env = make_vec_env("myoLegWalk-v0", n_envs=4, seed=0)
    model = CGAC(
        "MlpPolicy", env, buffer_window=16, batch_size=64, seed=0, policy_kwargs=dict(net_arch=[64, 64])
    )  # fmt: skip
    model.learn(320)
    assert model.num_timesteps >= 320
    obs = env.reset()
    actions, _ = model.predict(obs, deterministic=True)
    assert actions.shape == (4, 80)
    assert np.all(actions >= env.action_space.low) and np.all(actions <= env.action_space.high)  # muscles in [0, 1]
    model.save(tmp_path / "cgac_myoleg")
    loaded = CGAC.load(tmp_path / "cgac_myoleg", env=env)
    np.testing.assert_allclose(loaded.predict(obs, deterministic=True)[0], actions, rtol=1e-6)
    loaded.learn(64, reset_num_timesteps=False)  # training goes on after loading
    env.close()


@pytest.mark.parametrize("env_id", MYOSUITE_TASKS)
def test_entries_train(tmp_path, env_id):
    """The CGAC, PPO and SAC entries of each task train a few steps through the zoo code path (few envs here)."""
    pytest.importorskip("rl_zoo3")
    from sb3_cgac.zoo import HYPERPARAMS_DIR, build_model

    for algo in ("cgac", "ppo", "sac"):
        assert env_id in yaml.safe_load((HYPERPARAMS_DIR / f"{algo}.yml").read_text()), (algo, env_id)
        overrides = {"n_envs": 4, "batch_size": 64} if algo == "cgac" else {"learning_starts": 32} if algo == "sac" else {}
        model, manager = build_model(algo, env_id, log_folder=str(tmp_path / algo), hyperparams=overrides)
        model.learn(128 if algo != "ppo" else model.n_steps, callback=manager.callbacks)
        assert model.num_timesteps > 0
        model.get_env().close()
