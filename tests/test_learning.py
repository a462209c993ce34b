"""Learning tests: a return threshold reached within a step budget, with fixed seeds."""

import pathlib

from sb3_cgac import CGAC

import pytest
import torch as th
import yaml
from stable_baselines3.common.callbacks import EvalCallback, StopTrainingOnRewardThreshold
from stable_baselines3.common.env_util import make_vec_env

HYPERPARAMS = pathlib.Path(__file__).parents[1] / "hyperparams" / "cgac.yml"


def zoo_hyperparams(env_id: str) -> tuple[int, int, dict]:
    """The shipped rl-zoo entry: (n_envs, n_timesteps, CGAC keyword arguments)."""
    entry = dict(yaml.safe_load(HYPERPARAMS.read_text())[env_id])
    n_envs, n_timesteps = entry.pop("n_envs"), int(entry.pop("n_timesteps"))
    entry.pop("policy")
    if isinstance(entry.get("policy_kwargs"), str):
        entry["policy_kwargs"] = eval(entry["policy_kwargs"], {"dict": dict, "nn": th.nn})
    return n_envs, n_timesteps, entry


def test_pendulum_reaches_minus_200():
    """Budget: 250k steps (the zoo entry reaches -200 at 50k-160k steps for seeds 0-9, at 110k for seed 0)."""
    threshold, budget = -200.0, 250_000
    n_envs, _, kwargs = zoo_hyperparams("Pendulum-v1")
    env = make_vec_env("Pendulum-v1", n_envs=n_envs, seed=0)
    eval_env = make_vec_env("Pendulum-v1", n_envs=10, seed=1000)
    stop = StopTrainingOnRewardThreshold(reward_threshold=threshold)
    evaluation = EvalCallback(
        eval_env, eval_freq=10_000 // n_envs, n_eval_episodes=10, deterministic=True, callback_on_new_best=stop, verbose=0
    )
    model = CGAC("MlpPolicy", env, seed=0, **kwargs)
    model.learn(budget, callback=evaluation)
    assert evaluation.best_mean_reward >= threshold, (
        f"best mean return {evaluation.best_mean_reward:.0f} after {model.num_timesteps} steps"
    )


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5])
def test_pendulum_other_seeds(seed):
    """Seed 5 did not learn in 300k steps with gamma 0.99 (the entry now has 0.98): a guard against a fragile entry."""
    n_envs, _, kwargs = zoo_hyperparams("Pendulum-v1")
    eval_env = make_vec_env("Pendulum-v1", n_envs=10, seed=1000)
    stop = StopTrainingOnRewardThreshold(reward_threshold=-200.0)
    evaluation = EvalCallback(eval_env, eval_freq=10_000 // n_envs, n_eval_episodes=10, callback_on_new_best=stop)
    model = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=n_envs, seed=seed), seed=seed, **kwargs)
    model.learn(300_000, callback=evaluation)
    assert evaluation.best_mean_reward >= -200.0
