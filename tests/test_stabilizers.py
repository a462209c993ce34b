"""Observation normalisation inside the policy, the learning-rate decay, predict_tau and desynchronised resets."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.utils import LinearSchedule

from sb3_cgac import CGAC
from sb3_cgac.policies import CGACPolicy, RunningObsNormalizer
from sb3_cgac.vec_env.wrappers import RandomFirstEpisodeLength

SMALL = dict(policy_kwargs=dict(net_arch=[16, 16]), seed=0)


def test_running_normalizer_matches_numpy():
    rng = np.random.default_rng(0)
    batches = [rng.normal(loc=3.0, scale=[0.5, 4.0], size=(n, 2)).astype(np.float32) for n in (7, 64, 1, 300)]
    normalizer = RunningObsNormalizer((2,))
    for batch in batches:
        normalizer.update(th.as_tensor(batch))
    everything = np.concatenate(batches)
    np.testing.assert_allclose(normalizer.mean.numpy(), everything.mean(axis=0), rtol=1e-4)
    np.testing.assert_allclose(normalizer.var.numpy(), everything.var(axis=0), rtol=1e-3)
    normalized = normalizer(th.as_tensor(everything)).numpy()
    np.testing.assert_allclose(normalized.mean(axis=0), 0.0, atol=1e-3)
    np.testing.assert_allclose(normalized.std(axis=0), 1.0, atol=2e-2)
    # Clipped at +-5, as in the authors' code
    assert normalizer(th.full((1, 2), 1e4)).max().item() == pytest.approx(5.0)


def test_normalizer_ignores_non_finite_rows():
    policy = CGACPolicy(
        gym.spaces.Box(-np.inf, np.inf, (1,)), gym.spaces.Box(-1, 1, (1,)), lambda _: 1e-3, normalize_observations=True
    )
    normalizer = policy.obs_normalizer
    assert normalizer is not None
    # The zeroed row of a non-finite observation does not enter the statistics
    policy.update_obs_normalizer(th.tensor([[2.0], [0.0], [4.0]]), th.tensor([True, False, True]))
    assert normalizer.mean.item() == pytest.approx(3.0, abs=1e-3)


def test_normalize_observations_needs_box_or_dict_spaces():
    with pytest.raises(ValueError, match="normalize_observations needs a Box or Dict observation space"):
        CGACPolicy(gym.spaces.Discrete(4), gym.spaces.Box(-1, 1, (2,)), lambda _: 1e-3, normalize_observations=True)


def test_mean_init_scale(tmp_path):
    env = make_vec_env("Pendulum-v1", n_envs=4)
    obs = th.as_tensor(env.reset(), dtype=th.float32)
    kwargs = dict(net_arch=[16, 16], use_xavier_init=False)
    th.manual_seed(0)
    full = CGAC("MlpPolicy", env, policy_kwargs=kwargs)
    th.manual_seed(0)
    small = CGAC("MlpPolicy", env, policy_kwargs=dict(**kwargs, mean_init_scale=0.01))
    # Only the mean layer is scaled (the default init draws a non-zero bias, which is scaled too)
    th.testing.assert_close(small.policy.actor.mu.weight, 0.01 * full.policy.actor.mu.weight)
    th.testing.assert_close(small.policy.actor.mu.bias, 0.01 * full.policy.actor.mu.bias)
    th.testing.assert_close(small.policy.actor.latent_pi[0].weight, full.policy.actor.latent_pi[0].weight)
    # The averaged actor, which acts, starts as a copy; the untrained deterministic actions are near zero
    th.testing.assert_close(small.policy.actor_avg.mu.weight, small.policy.actor.mu.weight)
    obs = obs.to(full.device)
    mean_full, _ = full.policy.actor_avg.get_action_dist_params(obs)
    mean_small, _ = small.policy.actor_avg.get_action_dist_params(obs)
    th.testing.assert_close(mean_small, 0.01 * mean_full)
    # Saved as a constructor argument: a loaded model rebuilds the same policy
    small.save(tmp_path / "model")
    loaded = CGAC.load(tmp_path / "model")
    assert loaded.policy.actor.mean_init_scale == 0.01
    th.testing.assert_close(loaded.policy.actor_avg.mu.weight, small.policy.actor_avg.mu.weight)


def test_learning_rate_decay(tmp_path):
    """The authors' decay as an SB3 schedule: linear from 2e-3 to 1e-4 over half of training, alpha's rate 10x along."""
    schedule = LinearSchedule(2e-3, 1e-4, 0.5)
    model = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4), learning_rate=schedule, **SMALL)
    model.learn(4 * 100)
    # The last iteration's updates run at progress remaining 0: the end of the decay
    for optimizer, factor in ((model.actor.optimizer, 1), (model.critic.optimizer, 1), (model.ent_coef_optimizer, 10)):
        assert optimizer.param_groups[0]["lr"] == pytest.approx(factor * 1e-4)
    # An iteration a quarter of the way: half of the decay
    model._current_progress_remaining = 0.75
    model.train()
    middle = 2e-3 + 0.5 * (1e-4 - 2e-3)
    assert model.actor.optimizer.param_groups[0]["lr"] == pytest.approx(middle)
    assert model.critic.optimizer.param_groups[0]["lr"] == pytest.approx(middle)
    assert model.ent_coef_optimizer.param_groups[0]["lr"] == pytest.approx(10 * middle)
    assert model.logger.name_to_value["train/learning_rate"] == pytest.approx(middle)
    # The schedule is saved with the model
    model.save(tmp_path / "model")
    loaded = CGAC.load(tmp_path / "model", env=make_vec_env("Pendulum-v1", n_envs=4))
    assert loaded.lr_schedule(0.75) == pytest.approx(middle)


def test_random_first_episode_length():
    """First episodes end at lengths spread over 1..200 as time-limit truncations; later ones last the full 200."""
    env = make_vec_env("Pendulum-v1", n_envs=32, seed=0, wrapper_class=RandomFirstEpisodeLength)
    env.reset()
    first_end: dict[int, int] = {}
    later_lengths = []
    since_reset = np.zeros(32, dtype=int)
    for _ in range(400):
        _, _, dones, infos = env.step(np.zeros((32, 1), np.float32))
        since_reset += 1
        for idx in np.flatnonzero(dones):
            assert infos[idx]["TimeLimit.truncated"] and "terminal_observation" in infos[idx]
            if idx in first_end:
                later_lengths.append(since_reset[idx])
            else:
                first_end[idx] = since_reset[idx]
            since_reset[idx] = 0
    first = np.array(list(first_end.values()))
    assert len(first) == 32 and first.min() >= 1 and first.max() <= 200
    assert len(set(first.tolist())) > 20  # spread out, not all at the time limit
    assert later_lengths and all(length == 200 for length in later_lengths)
    # Seeded: the same seeds give the same cuts
    cuts = []
    for _ in range(2):
        fresh = make_vec_env("Pendulum-v1", n_envs=8, seed=3, wrapper_class=RandomFirstEpisodeLength)
        fresh.reset()
        cuts.append([fresh.envs[idx]._steps_left for idx in range(8)])
    assert cuts[0] == cuts[1]


def test_random_first_episode_length_after_a_full_reset():
    """A reset of the whole VecEnv (learn() resets it again) puts the envs back in step: it draws new cuts."""
    env = make_vec_env("Pendulum-v1", n_envs=16, seed=0, wrapper_class=RandomFirstEpisodeLength)
    for _ in range(2):  # reset twice, as a user checking the observations and then learn() would
        env.reset()
    for _ in range(5):
        env.step(np.zeros((16, 1), np.float32))
    env.reset()  # mid-episode
    cuts = [env.envs[idx]._steps_left for idx in range(16)]
    assert None not in cuts and len(set(cuts)) > 8
    first_ends = np.zeros(16, dtype=int)
    for step in range(1, 201):
        _, _, dones, _ = env.step(np.zeros((16, 1), np.float32))
        first_ends[(first_ends == 0) & dones] = step
    assert len(set(first_ends.tolist())) > 8


def test_random_first_episode_length_needs_a_time_limit():
    class NoLimit(gym.Env):
        observation_space = gym.spaces.Box(-1, 1, (1,))
        action_space = gym.spaces.Box(-1, 1, (1,))

    with pytest.raises(ValueError, match="max_episode_steps"):
        RandomFirstEpisodeLength(NoLimit())
    assert RandomFirstEpisodeLength(NoLimit(), max_episode_steps=10).max_episode_steps == 10


def test_warns_about_synchronised_resets():
    kwargs = dict(policy_kwargs=dict(net_arch=[8]), buffer_window=4, seed=0)
    limit = dict(max_episode_steps=20)  # short episodes: the same time limits in fewer steps
    with pytest.warns(UserWarning, match="same step"):
        CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=16, seed=0, env_kwargs=limit), **kwargs).learn(16 * 21)
    import warnings

    from sb3_cgac.vec_env import make_vec_env as make_cgac_vec_env

    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        env = make_cgac_vec_env("Pendulum-v1", n_envs=16, seed=0, env_kwargs=limit, random_first_episode=True)
        CGAC("MlpPolicy", env, **kwargs).learn(16 * 41)


def test_predict_tau_leaves_training_unchanged():
    """The slower average for predict() is only read by predict(): the same seed trains the same networks."""

    def train(predict_tau):
        model = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4, seed=0), predict_tau=predict_tau, **SMALL)
        model.learn(4 * 60)
        return model

    plain, slow = train(None), train(0.2)  # a rate unlike the averaged actor's (policy_tau 0.05)
    assert plain.policy.actor_predict is None and slow.policy.actor_predict is not None
    slow_state = slow.policy.state_dict()
    for name, value in plain.policy.state_dict().items():
        assert th.equal(value, slow_state[name]), name
    # predict() acts with the slow average, which differs from the averaged actor that collected the data
    obs = np.random.default_rng(0).normal(size=(5, 3)).astype(np.float32)
    with th.no_grad():
        expected = slow.policy.actor_predict(th.as_tensor(obs), deterministic=True).numpy()
        behaviour = slow.actor_avg(th.as_tensor(obs), deterministic=True).numpy()
    assert np.allclose(slow.predict(obs, deterministic=True)[0], slow.policy.unscale_action(expected))
    assert not np.allclose(expected, behaviour)


def test_predict_tau_averages_the_actor():
    model = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4, seed=0), predict_tau=0.2, **SMALL)
    model.learn(4 * 60)
    assert model.policy.actor_predict is not None
    before = [param.clone() for param in model.policy.actor_predict.parameters()]
    # Trained for a while, the average lags the actor, so the update below moves it
    assert any(not th.equal(old, trained) for old, trained in zip(before, model.actor.parameters(), strict=True))
    model.policy.polyak_update(model.tau, model.policy_tau, model.predict_tau)
    for old, new, trained in zip(before, model.policy.actor_predict.parameters(), model.actor.parameters(), strict=True):
        assert th.allclose(new, old + 0.2 * (trained - old), atol=1e-7)
        assert not new.requires_grad


def test_synchronised_resets_warning_is_given_once():
    # Two synchronised time limits (steps 20 and 40 of every env): one warning per model, not one per episode
    kwargs = dict(policy_kwargs=dict(net_arch=[8]), buffer_window=4, seed=0)
    env = make_vec_env("Pendulum-v1", n_envs=16, seed=0, env_kwargs=dict(max_episode_steps=20))
    with pytest.warns(UserWarning) as record:
        CGAC("MlpPolicy", env, **kwargs).learn(16 * 41)
    assert sum("same step" in str(warning.message) for warning in record) == 1
