import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.callbacks import BaseCallback, EvalCallback
from stable_baselines3.common.env_checker import check_env
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.logger import configure
from stable_baselines3.common.utils import LinearSchedule
from stable_baselines3.common.vec_env import SubprocVecEnv, VecNormalize
from toy_envs import DictObsEnv  # tests/ is on sys.path under pytest

from sb3_cgac import CGAC, MultiInputPolicy
from sb3_cgac.callbacks import RewardEntropySchedule

SMALL = dict(policy_kwargs=dict(net_arch=[16, 16]), seed=0)


def make_env(n_envs: int = 4, env_id: str = "Pendulum-v1", **kwargs):
    return make_vec_env(env_id, n_envs=n_envs, seed=0, **kwargs)


@pytest.mark.parametrize(
    "kwargs",
    [
        {},  # the paper's schedule: 1 new step per iteration, 32-step window
        dict(n_steps=8, buffer_window=8),  # PPO-like: a fresh buffer every rollout
        dict(n_steps=4, buffer_window=16, batch_size=32, critic_updates_per_step=1, policy_delay=1),
        dict(ent_coef=0.05),
        dict(ent_coef="auto", ent_coef_monotone=False, gae_horizon=4, gae_lambda=1.0),
        dict(tau=1.0, policy_tau=1.0),  # no value averaging, no policy averaging
        dict(learning_rate=lambda progress: 1e-3 * progress),
        dict(learning_rate=LinearSchedule(2e-3, 1e-4, 0.5), ent_coef_monotone=True),
        dict(policy_kwargs=dict(net_arch=dict(pi=[8], qf=[16, 16]), n_critics=3)),
        dict(policy_kwargs=dict(net_arch=[16], share_features_extractor=True, use_xavier_init=False)),
        dict(policy_kwargs=dict(net_arch=[16], normalize_observations=True)),
        dict(policy_kwargs=dict(net_arch=[16], optimizer_class=th.optim.AdamW, optimizer_kwargs=dict(weight_decay=0.01))),
        dict(update_precision="bfloat16"),
        dict(update_precision="auto"),
        dict(policy_kwargs=dict(net_arch=[16], optimizer_kwargs=dict(foreach=True))),
        dict(predict_tau=0.001),
    ],
)
def test_run(kwargs):
    kwargs = {**SMALL, **kwargs}
    model = CGAC("MlpPolicy", make_env(), **kwargs)
    model.learn(400)
    assert model.num_timesteps >= 400
    assert model._n_updates > 0
    assert all(th.isfinite(p).all() for p in model.policy.parameters())


def test_logging(tmp_path):
    model = CGAC("MlpPolicy", make_env(), **SMALL)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(1000, log_interval=20)  # Pendulum episodes last 200 steps
    header = (tmp_path / "progress.csv").read_text().splitlines()[0].split(",")
    for key in [
        "train/critic_loss",
        "train/actor_loss",
        "train/ent_coef",
        "train/ent_coef_loss",
        "train/target_entropy",
        "train/q_mean",
        "train/critic_grad_norm",
        "train/actor_grad_norm",
        "train/n_updates",
        "train/learning_rate",
        "rollout/ep_rew_mean",
        "rollout/nonfinite_transitions",
        "time/fps",
    ]:
        assert key in header, key


def test_progress_bar():
    model = CGAC("MlpPolicy", make_env(), **SMALL)
    model.learn(200, progress_bar=True)


def test_n_envs_1_warns_and_runs():
    with pytest.warns(UserWarning, match="many parallel environments"):
        model = CGAC("MlpPolicy", "Pendulum-v1", **SMALL)
    assert model.n_envs == 1
    model.learn(100)
    assert model._n_updates > 0


def test_subproc_vec_env():
    env = make_env(2, vec_env_cls=SubprocVecEnv)
    model = CGAC("MlpPolicy", env, buffer_window=8, **SMALL)
    model.learn(64)
    env.close()


def test_vec_normalize():
    env = VecNormalize(make_env(), norm_obs=True, norm_reward=True)
    model = CGAC("MlpPolicy", env, **SMALL)
    schedule = RewardEntropySchedule()
    model.learn(1000, callback=schedule)  # Pendulum truncates at 200 steps: terminal observations come normalized
    assert model.get_vec_normalize_env() is env
    # The reward schedule follows the raw reward (Pendulum: about -1 to -16 per step), not the normalized one
    assert schedule.reward_average < -1.0


def test_callback_can_stop_training():
    class StopAfter(BaseCallback):
        def _on_step(self) -> bool:
            return self.n_calls < 10

    model = CGAC("MlpPolicy", make_env(), **SMALL)
    model.learn(10_000, callback=StopAfter())
    assert model.num_timesteps == 10 * 4
    # Training can go on after a stop
    model.learn(40, reset_num_timesteps=False)
    assert model.num_timesteps == 80


def test_eval_callback(tmp_path):
    eval_env = make_env(2)
    callback = EvalCallback(
        eval_env, eval_freq=50, n_eval_episodes=2, log_path=str(tmp_path), best_model_save_path=str(tmp_path)
    )
    model = CGAC("MlpPolicy", make_env(), **SMALL)
    model.learn(400, callback=callback)
    assert (tmp_path / "evaluations.npz").exists()
    assert (tmp_path / "best_model.zip").exists()


def test_predict():
    model = CGAC("MlpPolicy", make_env(), **SMALL)
    model.learn(200)
    env = make_env(1)
    obs = env.reset()
    deterministic_action, _ = model.predict(obs, deterministic=True)
    assert np.array_equal(deterministic_action, model.predict(obs, deterministic=True)[0])
    stochastic = np.stack([model.predict(obs, deterministic=False)[0] for _ in range(10)])
    assert stochastic.std(axis=0).max() > 0
    assert env.action_space.contains(deterministic_action[0])
    # A single, non-vectorised observation
    single_action, _ = model.predict(obs[0], deterministic=True)
    assert single_action.shape == env.action_space.shape
    mean_reward, _ = evaluate_policy(model, env, n_eval_episodes=1)
    assert np.isfinite(mean_reward)


def test_actions_respect_bounds():
    env = make_env(4)
    model = CGAC("MlpPolicy", env, **SMALL)
    low, high = env.action_space.low, env.action_space.high
    seen = []

    class Record(BaseCallback):
        def _on_step(self) -> bool:
            seen.append(self.model.policy.unscale_action(self.locals["actions"].cpu().numpy()))
            return True

    model.learn(200, callback=Record())
    actions = np.concatenate(seen)
    assert (actions >= low).all() and (actions <= high).all()
    assert actions.min() < 0 < actions.max()


class InPlaceActionEnv(gym.Env):
    """Overwrites the action array it is given with the lower bound, as an env that clips in place would."""

    observation_space = spaces.Box(-1, 1, (2,), np.float32)

    def __init__(self, low: float, high: float):
        super().__init__()
        self.action_space = spaces.Box(low, high, (2,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(2, np.float32), {}

    def step(self, action):
        action[...] = self.action_space.low
        return np.zeros(2, np.float32), 0.0, False, False, {}


@pytest.mark.parametrize("low, high", [(-1.0, 1.0), (-2.0, 2.0), (0.0, 3.0)])
def test_env_gets_its_own_action_array(low, high):
    # An env writing into its action must not alter the (squashed) actions CGAC stores
    env = make_vec_env(InPlaceActionEnv, n_envs=2, env_kwargs=dict(low=low, high=high))
    model = CGAC("MlpPolicy", env, **SMALL)
    model.learn(20)  # 10 steps of 2 envs, one per iteration
    stored = model.rollout_buffer.actions[:10]
    assert (stored.abs() < 1).all() and stored.std() > 0
    scaled = np.array([[-1.0, 0.5], [1.0, 0.0]], dtype=np.float32)
    action = model.policy.unscale_action(scaled)
    assert not np.shares_memory(action, scaled)
    np.testing.assert_allclose(action, low + 0.5 * (scaled + 1.0) * (high - low), rtol=1e-6)


def test_dict_obs_env_is_valid():
    check_env(DictObsEnv())


def test_multi_input_policy():
    model = CGAC("MultiInputPolicy", make_vec_env(DictObsEnv, n_envs=4, seed=0), **SMALL)
    assert isinstance(model.policy, MultiInputPolicy)
    model.learn(300)
    obs = {"position": np.zeros((1, 2), np.float32), "velocity": np.zeros((1, 1), np.float32)}
    action, _ = model.predict(obs, deterministic=True)
    assert action.shape == (1, 2)


@pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA device")
def test_cuda(tmp_path):
    """Training, targets, save/load and predict on the GPU (CI has none; run on a machine with one)."""
    env = VecNormalize(make_env(8))
    model = CGAC("MlpPolicy", env, device="cuda", **SMALL)
    model.learn(
        1000, callback=RewardEntropySchedule()
    )  # Pendulum truncates at 200 steps: terminal observations go to the GPU too
    assert model.rollout_buffer.returns.is_cuda and next(model.policy.parameters()).is_cuda
    model.save(tmp_path / "cuda_model")
    loaded = CGAC.load(tmp_path / "cuda_model", env=env, device="cpu")
    obs = env.reset()
    expected = model.predict(obs, deterministic=True)[0]
    np.testing.assert_allclose(expected, loaded.predict(obs, deterministic=True)[0], atol=1e-5)
