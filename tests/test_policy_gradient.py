"""The likelihood-ratio term beside the critic gradient (``pg_coef``): log-likelihoods, the clipped surrogate, the
behaviour policy's log-likelihoods kept by the window, and training with it."""

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.distributions import SquashedDiagGaussianDistribution
from stable_baselines3.common.env_util import make_vec_env

from sb3_cgac import CGAC
from sb3_cgac.buffers import CGACRolloutBuffer
from sb3_cgac.losses import PG_CLIP_RANGE, PG_DUAL_CLIP, PolicyGradientTerm, actor_loss, clipped_surrogate
from sb3_cgac.policies import reparameterised_sample, squashed_log_prob
from tests.test_asymmetric import ASYMMETRIC, PrivilegedEnv
from tests.test_gae import ACTION_SPACE, OBS_SPACE, STEPS, env_step, fill_buffer


def test_squashed_log_prob_is_sb3s():
    th.manual_seed(0)
    mean, log_std = th.randn(64, 3), th.randn(3) * 0.5
    actions = th.rand(64, 3) * 1.8 - 0.9
    distribution = SquashedDiagGaussianDistribution(3).proba_distribution(mean, log_std)
    assert th.allclose(squashed_log_prob(mean, log_std, actions), distribution.log_prob(actions), atol=1e-4)


def test_squashed_log_prob_of_a_sample_is_its_log_prob():
    th.manual_seed(0)
    mean, log_std = th.randn(64, 3) * 0.5, th.full((3,), -1.0)
    actions, log_prob = reparameterised_sample(mean, log_std)
    assert th.allclose(squashed_log_prob(mean, log_std, actions), log_prob, atol=1e-3)


def test_saturated_actions_have_finite_log_probs():
    mean, log_std = th.zeros(2, 1), th.zeros(1)
    log_prob = squashed_log_prob(mean, log_std, th.tensor([[1.0], [-1.0]]))
    assert th.isfinite(log_prob).all()


@pytest.mark.parametrize(
    "ratio, advantage, value, gradient",
    [
        (1.0, 2.0, 2.0, 2.0),  # on-policy: A, and d/d(log ratio) = ratio * A
        (1.5, 2.0, (1 + PG_CLIP_RANGE) * 2.0, 0.0),  # a positive advantage is not pushed beyond 1 + clip
        (0.5, 2.0, 1.0, 1.0),  # below the clip, a positive advantage still pulls the ratio up
        (0.5, -2.0, -(1 - PG_CLIP_RANGE) * 2.0, 0.0),  # a negative advantage is not pushed below 1 - clip
        (2.0, -1.0, -2.0, -2.0),  # above the clip, a negative advantage pulls the ratio down ...
        (5.0, -1.0, -PG_DUAL_CLIP, 0.0),  # ... but not beyond the dual clip
        (1e30, -1.0, -PG_DUAL_CLIP, 0.0),  # an overflowing ratio gives no NaN
    ],
)
def test_clipped_surrogate(ratio, advantage, value, gradient):
    log_ratio = th.tensor([float(np.log(ratio))], requires_grad=True)
    surrogate, clipped = clipped_surrogate(log_ratio, th.tensor([advantage]))
    surrogate.sum().backward()
    assert surrogate.item() == pytest.approx(value, rel=1e-5)
    assert log_ratio.grad is not None and log_ratio.grad.item() == pytest.approx(gradient, rel=1e-4)
    assert clipped.item() == float(abs(ratio - 1.0) > PG_CLIP_RANGE)


def test_window_keeps_the_behaviour_log_probs():
    buffer = CGACRolloutBuffer(8, OBS_SPACE, ACTION_SPACE, device="cpu")
    fill_buffer(buffer, STEPS[:3], terminal_value=7.0)
    calls = []

    def behaviour(obs, actions):
        calls.append(len(actions))
        return (obs + actions).sum(dim=1)

    buffer.compute_returns(lambda obs, actions: th.zeros(len(actions)))
    assert buffer.log_probs is None and buffer.sample(4).log_probs is None
    for obs, action, reward, terminated, truncated, next_action in STEPS[3:5]:
        step = env_step([reward], [terminated], [truncated], [[obs + 1]], final_obs=[[7.0]] if truncated else None)
        buffer.add(th.tensor([[action]]), step, th.tensor([[next_action]]))
    buffer.compute_returns(lambda obs, actions: th.zeros(len(actions)), behaviour)
    # The first call with a behaviour policy fills the whole window, later ones the new steps only
    assert calls == [5]
    expected = (buffer.observations[:5, :, 0] + buffer.actions[:5, :, 0]).reshape(-1)
    assert th.allclose(buffer.log_probs[:5].reshape(-1), expected)
    samples = buffer.sample(16)
    assert samples.log_probs is not None
    assert th.allclose(samples.log_probs, (samples.observations + samples.actions).sum(dim=1))


def test_policy_gradient_term_on_policy_adds_the_mean_advantage():
    # With the ratio at 1 the term's value is the weighted mean advantage A = Y - min_i Q_i(s, a_pi)
    model = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4, seed=0), policy_kwargs=dict(net_arch=[16, 16]), seed=0)
    obs, taken = th.randn(8, 3), th.rand(8, 1) * 1.8 - 0.9
    returns, weights = th.randn(8) * 5, th.ones(8)
    behaviour = model.actor.log_prob(obs, taken)
    term = PolicyGradientTerm(0.5, taken, returns, behaviour)
    th.manual_seed(1)
    args = (model.actor, model.critic, obs, weights, weights.sum(), th.tensor(0.0))
    loss, _, statistics = actor_loss(*args, policy_gradient=term)
    th.manual_seed(1)
    plain, _, none = actor_loss(*args)
    th.manual_seed(1)
    actions_pi, _ = model.actor.action_log_prob(obs)
    advantages = returns - model.critic.q_values(obs, actions_pi).min(dim=0).values
    assert none == {}
    assert th.allclose(loss, plain - 0.5 * advantages.mean(), atol=1e-5)
    assert statistics["pg_clip_fraction"].item() == 0.0
    assert th.allclose(statistics["pg_advantage_abs"], advantages.abs().mean().detach())


@pytest.mark.parametrize("update_precision", ["float32", "bfloat16"])
def test_run_with_pg_coef(update_precision):
    env = make_vec_env("Pendulum-v1", n_envs=4, seed=0)
    policy_kwargs = dict(net_arch=[16, 16], critic_layer_norm=True, n_bins=21, actor_q_reduction="mean")
    model = CGAC("MlpPolicy", env, pg_coef=1.0, policy_kwargs=policy_kwargs, update_precision=update_precision, seed=0)
    model.learn(400)
    assert model.rollout_buffer.log_probs is not None
    assert "train/pg_clip_fraction" in model.logger.name_to_value
    assert all(th.isfinite(p).all() for p in model.policy.parameters())


def test_run_with_pg_coef_dict_observations():
    env = make_vec_env(PrivilegedEnv, n_envs=4, seed=0)
    model = CGAC("MultiInputPolicy", env, pg_coef=1.0, policy_kwargs=dict(net_arch=[16, 16], **ASYMMETRIC), seed=0)
    model.learn(400)
    assert model.rollout_buffer.log_probs is not None and model._n_updates > 0


def test_default_keeps_no_log_probs():
    model = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4, seed=0), policy_kwargs=dict(net_arch=[16, 16]), seed=0)
    model.learn(200)
    assert model.pg_coef == 0.0 and model.rollout_buffer.log_probs is None


def test_save_load_keeps_pg_coef(tmp_path):
    model = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4, seed=0), pg_coef=0.5, seed=0)
    model.save(tmp_path / "model.zip")
    assert CGAC.load(tmp_path / "model.zip").pg_coef == 0.5


@pytest.mark.parametrize("pg_coef", [-1.0, float("nan"), "1", True])
def test_bad_pg_coef(pg_coef):
    with pytest.raises(ValueError, match="pg_coef"):
        CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4, seed=0), pg_coef=pg_coef)
