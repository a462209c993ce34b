"""Observation normalisation inside the policy, LayerNorm critics, the learning-rate decay and desynchronised resets."""

from sb3_cgac import CGAC
from sb3_cgac.losses import behaviour_kl
from sb3_cgac.policies import CGACPolicy, RunningObsNormalizer
from sb3_cgac.wrappers import RandomFirstEpisodeLength

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env

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
    policy.update_obs_normalizer(th.tensor([[2.0], [0.0], [4.0]]), np.array([True, False, True]))
    assert normalizer.mean.item() == pytest.approx(3.0, abs=1e-3)


def test_normalize_observations_rejects_dict_spaces():
    from test_run import DictObsEnv

    with pytest.raises(ValueError, match="normalize_observations needs a Box"):
        CGAC("MultiInputPolicy", make_vec_env(DictObsEnv, n_envs=2), policy_kwargs=dict(normalize_observations=True))


def test_critic_layer_norm():
    model = CGAC(
        "MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4), policy_kwargs=dict(net_arch=[8, 8], critic_layer_norm=True)
    )
    for critic in (model.critic, model.critic_target):
        for q_net in critic.q_networks:
            kinds = [type(layer).__name__ for layer in q_net]
            assert kinds == ["Linear", "LayerNorm", "ELU", "Linear", "LayerNorm", "ELU", "Linear"]
    # The LayerNorm parameters are trained and averaged like the others
    assert len(list(model.critic.parameters())) == len(list(model.critic_target.parameters())) == 2 * 10


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


def test_learning_rate_decay():
    """The authors' schedule: linear from the initial to the final rate over lr_decay_iterations iterations."""
    model = CGAC(
        "MlpPolicy",
        make_vec_env("Pendulum-v1", n_envs=4),
        learning_rate=2e-3,
        final_learning_rate=1e-4,
        lr_decay_iterations=100,
        **SMALL,
    )
    model.learn(4 * 72)  # updates start once the window holds 32 steps: 40 iterations of updates
    iterations = model._n_updates // model._critic_updates_per_step
    # The rate set at the start of the last iteration, before its updates
    expected = 2e-3 + (iterations - 1) / 100 * (1e-4 - 2e-3)
    assert model.actor.optimizer.param_groups[0]["lr"] == pytest.approx(expected)
    assert model.critic.optimizer.param_groups[0]["lr"] == pytest.approx(expected)
    # Alpha's rate stays at 10x the initial rate, as in the authors' code
    assert model.ent_coef_optimizer.param_groups[0]["lr"] == pytest.approx(2e-2)
    model.learn(4 * 100, reset_num_timesteps=False)
    assert model.actor.optimizer.param_groups[0]["lr"] == pytest.approx(1e-4)


def test_ent_coef_learning_rate_decay(tmp_path):
    """decay_ent_coef_learning_rate scales alpha's rate by the actor rate's decay factor: 10x the actor's throughout."""
    kwargs = dict(learning_rate=2e-3, final_learning_rate=1e-4, lr_decay_iterations=100, **SMALL)
    model = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4), decay_ent_coef_learning_rate=True, **kwargs)
    model.learn(4 * 72)
    actor_lr = model.actor.optimizer.param_groups[0]["lr"]
    assert actor_lr < 2e-3
    assert model.ent_coef_optimizer.param_groups[0]["lr"] == pytest.approx(10 * actor_lr)
    assert model.logger.name_to_value["train/ent_coef_learning_rate"] == pytest.approx(10 * actor_lr)
    # A separate alpha rate decays by the same factor
    model = CGAC(
        "MlpPolicy",
        make_vec_env("Pendulum-v1", n_envs=4),
        decay_ent_coef_learning_rate=True,
        ent_coef_learning_rate=3e-3,
        **kwargs,
    )
    model.learn(4 * 72)
    factor = model.actor.optimizer.param_groups[0]["lr"] / 2e-3
    assert model.ent_coef_optimizer.param_groups[0]["lr"] == pytest.approx(3e-3 * factor)
    # The option is saved with the model: a loaded model goes on decaying alpha's rate
    model.save(tmp_path / "model")
    loaded = CGAC.load(tmp_path / "model", env=make_vec_env("Pendulum-v1", n_envs=4))
    assert loaded.decay_ent_coef_learning_rate is True
    loaded.learn(4 * 8, reset_num_timesteps=False)
    factor = loaded.actor.optimizer.param_groups[0]["lr"] / 2e-3
    assert loaded.ent_coef_optimizer.param_groups[0]["lr"] == pytest.approx(3e-3 * factor)


def test_bad_learning_rate_decay():
    with pytest.raises(ValueError, match="final_learning_rate"):
        CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4), final_learning_rate=-1.0)
    with pytest.raises(ValueError, match="lr_decay_iterations"):
        CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4), final_learning_rate=1e-4, lr_decay_iterations=0)
    with pytest.raises(ValueError, match="set final_learning_rate"):
        CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4), decay_ent_coef_learning_rate=True)
    with pytest.raises(ValueError, match="ent_coef='auto'"):
        CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4), final_learning_rate=1e-4, ent_coef=0.1,
             decay_ent_coef_learning_rate=True)  # fmt: skip


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
    with pytest.warns(UserWarning, match="same step"):
        CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=16, seed=0), **kwargs).learn(16 * 201)
    import warnings

    from sb3_cgac.vec_env import make_vec_env as make_cgac_vec_env

    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        env = make_cgac_vec_env("Pendulum-v1", n_envs=16, seed=0, random_first_episode=True)
        CGAC("MlpPolicy", env, **kwargs).learn(16 * 401)


def test_behaviour_kl_matches_torch_distributions():
    model = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4), device="cpu", **SMALL)
    obs = th.randn(32, 3)
    weights, weight_sum = th.ones(32), th.tensor(32.0)
    # Identical actors: no penalty
    assert behaviour_kl(model.actor, model.actor_avg, obs, weights, weight_sum).item() == pytest.approx(0.0, abs=1e-6)
    with th.no_grad():
        for param in model.actor.parameters():
            param.add_(0.1 * th.randn_like(param))
    kl = behaviour_kl(model.actor, model.actor_avg, obs, weights, weight_sum)
    mean_b, log_std_b = model.actor_avg.get_action_dist_params(obs)
    mean, log_std = model.actor.get_action_dist_params(obs)
    expected = th.distributions.kl_divergence(
        th.distributions.Normal(mean_b, log_std_b.exp()), th.distributions.Normal(mean, log_std.exp())
    ).sum(dim=-1)
    assert kl.item() == pytest.approx(expected.mean().item(), rel=1e-4)
    assert kl.item() > 0
    # Its gradient reaches the trained actor only
    kl.backward()
    assert all(param.grad is None for param in model.actor_avg.parameters())
    assert model.actor.mu.weight.grad is not None


def test_behaviour_kl_coef_keeps_the_actor_near_the_averaged_actor():
    def gap(coef: float) -> float:
        env = make_vec_env("Pendulum-v1", n_envs=8)
        model = CGAC("MlpPolicy", env, behaviour_kl_coef=coef, policy_tau=0.001, batch_size=64, **SMALL)
        model.learn(800)
        obs = th.randn(256, 3, device=model.device)
        with th.no_grad():
            mean, _ = model.actor.get_action_dist_params(obs)
            mean_b, _ = model.actor_avg.get_action_dist_params(obs)
        return (mean - mean_b).abs().mean().item()

    assert gap(100.0) < 0.5 * gap(0.0)


@pytest.mark.parametrize("refresh", [False, True])
def test_refresh_target_values(refresh):
    env = make_vec_env("Pendulum-v1", n_envs=4)
    model = CGAC("MlpPolicy", env, refresh_target_values=refresh, buffer_window=8, batch_size=16, **SMALL)
    model.learn(4 * 12)
    before = model.rollout_buffer.next_actions.clone()
    model.learn(4 * 2, reset_num_timesteps=False)
    buffer = model.rollout_buffer
    # The two newest steps are new either way; the six older ones keep their next actions unless refreshed
    older = [(buffer.pos + k) % buffer.buffer_window for k in range(buffer.buffer_window - 2)]
    changed = (buffer.next_actions[older] != before[older]).any(dim=-1)
    assert changed.all() if refresh else not changed.any()


def test_predict_tau_leaves_training_unchanged():
    """The slower average for predict() is only read by predict(): the same seed trains the same networks."""

    def train(predict_tau):
        model = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4, seed=0), predict_tau=predict_tau, **SMALL)
        model.learn(4 * 60)
        return model

    plain, slow = train(None), train(0.05)
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
    model._polyak_updates()
    for old, new, trained in zip(before, model.policy.actor_predict.parameters(), model.actor.parameters(), strict=True):
        assert th.allclose(new, old + 0.2 * (trained - old), atol=1e-7)
        assert not new.requires_grad


def test_synchronised_resets_warning_is_given_once():
    # Two synchronised time limits (steps 200 and 400 of every env): one warning per model, not one per episode
    kwargs = dict(policy_kwargs=dict(net_arch=[8]), buffer_window=4, seed=0)
    with pytest.warns(UserWarning) as record:
        CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=16, seed=0), **kwargs).learn(16 * 401)
    assert sum("same step" in str(warning.message) for warning in record) == 1
