import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.env_checker import check_env
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure
from stable_baselines3.common.vec_env import VecEnvWrapper

from sb3_cgac import CGAC
from sb3_cgac.callbacks import ProgressEntropySchedule
from sb3_cgac.collection import OBS_ABS_LIMIT, sanitize_observations
from sb3_cgac.policies import CGACPolicy

SMALL = dict(policy_kwargs=dict(net_arch=[16]), seed=0)


class ActionSpaceEnv(gym.Env):
    observation_space = spaces.Box(-1, 1, (2,), np.float32)

    def __init__(self, action_space: spaces.Space):
        super().__init__()
        self.action_space = action_space

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(2, np.float32), {}

    def step(self, action):
        return np.zeros(2, np.float32), 0.0, False, False, {}


@pytest.mark.parametrize(
    "action_space",
    [spaces.Discrete(3), spaces.MultiDiscrete([2, 3]), spaces.MultiBinary(2)],
)
def test_discrete_action_spaces(action_space):
    with pytest.raises(ValueError, match=r"only supports continuous \(Box\) action spaces.*PPO"):
        CGAC("MlpPolicy", ActionSpaceEnv(action_space))


def test_policy_alone_rejects_discrete_actions():
    with pytest.raises(ValueError, match=r"CGACPolicy needs a continuous"):
        CGACPolicy(ActionSpaceEnv.observation_space, spaces.Discrete(3), lambda _: 1e-3)


def test_unbounded_box():
    with pytest.raises(ValueError, match=r"unbounded.*RescaleAction"):
        CGAC("MlpPolicy", ActionSpaceEnv(spaces.Box(-np.inf, np.inf, (2,), np.float32)))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(n_steps=64, buffer_window=32), r"n_steps \(64\) is larger than buffer_window \(32\)"),
        (dict(batch_size=1024, buffer_window=32), r"batch_size \(1024\) is larger than the buffer.*32 \* 4 = 128"),
        (dict(ent_coef="automatic"), "malformed ent_coef 'automatic'"),
        (dict(ent_coef="auto_-1"), "malformed ent_coef"),
        (dict(ent_coef=-0.1), "ent_coef must be >= 0"),
        (dict(tau=0.0), r"tau must be 'auto' or in \(0, 1\]"),
        (dict(tau=None), r"tau=None is the spelling of sb3_cgac 0.1.0; pass tau='auto'"),
        (dict(batch_size=None), r"batch_size=None is the spelling of sb3_cgac 0.1.0"),
        (dict(batch_size="big"), "batch_size must be an integer >= 1"),
        (dict(policy_tau=1.5), r"policy_tau must be 'auto' or in \(0, 1\]"),
        (dict(n_steps=0), "n_steps must be an integer >= 1"),
        (dict(policy_delay=0), "policy_delay must be an integer >= 1"),
        (dict(critic_updates_per_step=1.5), "critic_updates_per_step must be an integer"),
        (dict(gae_horizon=0), "gae_horizon must be an integer >= 1"),
        (dict(gamma=1.5), "gamma and gae_lambda must be in"),
        (dict(max_grad_norm=0.0), "max_grad_norm must be > 0"),
        (dict(update_precision="float16"), r"update_precision 'float16'; choose one of \('auto', 'float32', 'bfloat16'\)"),
        (dict(cuda_graphs="yes"), "cuda_graphs must be True or False"),
        (dict(predict_tau=0.0), r"predict_tau must be None or in \(0, 1\]"),
        (dict(policy_kwargs=dict(predict_actor=True)), "predict_actor=True but predict_tau is None"),
        (dict(predict_tau=0.01, policy_kwargs=dict(predict_actor=False)), "predict_actor=False but predict_tau is 0.01"),
        (dict(policy_kwargs=dict(mean_init_scale=-0.01)), "mean_init_scale must be a finite number >= 0"),
        (dict(policy_kwargs=dict(mean_init_scale=float("nan"))), "mean_init_scale must be a finite number >= 0"),
    ],
)
def test_inconsistent_hyperparameters(kwargs, message):
    env = make_vec_env("Pendulum-v1", n_envs=4)
    with pytest.raises(ValueError, match=message):
        CGAC("MlpPolicy", env, **kwargs)


def test_schedule_callback_needs_cgac():
    from stable_baselines3 import PPO

    model = PPO("MlpPolicy", "Pendulum-v1", n_steps=64, batch_size=64)
    with pytest.raises(TypeError, match=r"target_entropy_beta.*use it with sb3_cgac\.CGAC"):
        model.learn(64, callback=ProgressEntropySchedule())


class NoTerminalObservation(VecEnvWrapper):
    """A VecEnv that reports time-limit truncations but drops the terminal observation."""

    def reset(self):
        return self.venv.reset()

    def step_wait(self):
        obs, rewards, dones, infos = self.venv.step_wait()
        for info in infos:
            info.pop("terminal_observation", None)
        return obs, rewards, dones, infos


def test_env_without_terminal_observation():
    env = NoTerminalObservation(make_vec_env("Pendulum-v1", n_envs=4))
    model = CGAC("MlpPolicy", env, **SMALL)
    with pytest.raises(ValueError, match="without info\\['terminal_observation'\\]"):
        model.learn(1000)


class CorruptEnv(gym.Env):
    """Pendulum-like env whose observation or reward is sometimes NaN, Inf or huge."""

    observation_space = spaces.Box(-np.inf, np.inf, (3,), np.float32)
    action_space = spaces.Box(-2, 2, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.state = self.np_random.uniform(-1, 1, 3).astype(np.float32)
        self.steps = 0
        return self.state.copy(), {}

    def step(self, action):
        self.steps += 1
        self.state = np.clip(0.9 * self.state + 0.1 * float(action[0]), -5, 5).astype(np.float32)
        obs, reward = self.state.copy(), -float(np.sum(self.state**2))
        draw = self.np_random.random()
        if draw < 0.03:
            obs[0] = np.nan
        elif draw < 0.05:
            obs[1] = np.inf
        elif draw < 0.07:
            obs[2] = 1e9
        elif draw < 0.09:
            reward = np.nan
        return obs, reward, False, self.steps >= 30, {}


def test_corrupt_env_is_a_valid_gym_env():
    # check_env warns about NaN observations, which is what this env is for
    with pytest.warns(UserWarning):
        check_env(CorruptEnv(), warn=True)


@pytest.mark.parametrize("critic_options", [{}, dict(n_bins=21, critic_layer_norm=True)])
def test_nonfinite_data_is_excluded_and_counted(tmp_path, critic_options):
    policy_kwargs = dict(net_arch=[16], **critic_options)
    model = CGAC("MlpPolicy", make_vec_env(CorruptEnv, n_envs=8, seed=0), policy_kwargs=policy_kwargs, seed=0)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(2000, log_interval=10)
    assert all(th.isfinite(p).all() for p in model.policy.parameters())
    assert model.rollout_buffer.n_nonfinite > 0
    assert (model.rollout_buffer.weights == 0).any()
    assert th.isfinite(model.rollout_buffer.returns).all()
    logged = (tmp_path / "progress.csv").read_text()
    assert "rollout/nonfinite_transitions" in logged.splitlines()[0]


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_sanitize_observations(dtype):
    clean = np.arange(12, dtype=dtype).reshape(4, 3)
    obs, ok = sanitize_observations(clean)
    assert obs.dtype == np.float32 and ok.all()
    np.testing.assert_array_equal(obs, clean)

    corrupt = clean.copy()
    corrupt[1, 0], corrupt[2, 2], corrupt[3, 1] = np.nan, -np.inf, 10 * OBS_ABS_LIMIT
    obs, ok = sanitize_observations(corrupt)
    assert obs.dtype == np.float32
    np.testing.assert_array_equal(ok, [True, False, False, False])
    np.testing.assert_array_equal(obs[0], clean[0])
    assert (obs[1:] == 0).all()
    assert np.isnan(corrupt[1, 0]), "the caller's array must be left as it is"

    obs, ok = sanitize_observations({"a": corrupt, "image": np.ones((4, 2), np.uint8)})
    np.testing.assert_array_equal(ok, [True, False, False, False])
    assert obs["image"].dtype == np.uint8 and obs["a"].dtype == np.float32


def test_nonfinite_parameters_raise():
    model = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4), **SMALL)
    model.learn(200)
    with th.no_grad():
        model.critic.qf0[0].weight[0, 0] = float("nan")
    with pytest.raises(RuntimeError, match="parameters became NaN/Inf"):
        model.learn(200, reset_num_timesteps=False)
