"""The self-imitation term beside the critic gradient (``self_imitation_coef``): log-likelihoods of taken actions, the
term's value and gradient, and training with it."""

import pytest
import torch as th
from stable_baselines3.common.distributions import SquashedDiagGaussianDistribution
from stable_baselines3.common.env_util import make_vec_env

from sb3_cgac import CGAC
from sb3_cgac.losses import SelfImitationTerm, actor_loss
from sb3_cgac.policies import reparameterised_sample, squashed_log_prob
from tests.test_asymmetric import ASYMMETRIC, PrivilegedEnv


def make_model(**kwargs) -> CGAC:
    env = make_vec_env("Pendulum-v1", n_envs=4, seed=0)
    return CGAC("MlpPolicy", env, policy_kwargs=dict(net_arch=[16, 16]), seed=0, **kwargs)


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


def test_self_imitation_term_value_and_gradient():
    # The term adds -coef * max(A, 0) * log pi(a_taken|s), A = Y - min_i Q_i(s, a_pi): only better actions count
    model = make_model()
    obs, taken = th.randn(8, 3), th.rand(8, 1) * 1.8 - 0.9
    returns, weights = th.randn(8) * 50, th.ones(8)
    args = (model.actor, model.critic, obs, weights, weights.sum(), th.tensor(0.0))
    th.manual_seed(1)
    loss, _, statistics = actor_loss(*args, self_imitation=SelfImitationTerm(0.5, taken, returns))
    th.manual_seed(1)
    plain, _, none = actor_loss(*args)
    th.manual_seed(1)
    actions_pi, _ = model.actor.action_log_prob(obs)
    advantages = (returns - model.critic.q_values(obs, actions_pi).min(dim=0).values).detach()
    mean_actions, log_std = model.actor.get_action_dist_params(obs)
    taken_log_prob = squashed_log_prob(mean_actions, log_std, taken)
    assert none == {}
    assert 0 < (advantages > 0).sum() < 8  # both signs in the minibatch
    expected = plain - 0.5 * (advantages.clamp_min(0) * taken_log_prob).mean()
    assert th.allclose(loss, expected, atol=1e-5)
    assert statistics["self_imitation_fraction"].item() == pytest.approx((advantages > 0).float().mean().item())
    # Its gradient raises the likelihood of the better actions only
    model.actor.zero_grad()
    th.manual_seed(1)
    actor_loss(*args, self_imitation=SelfImitationTerm(0.5, taken, returns))[0].backward()
    with_term = [p.grad.clone() for p in model.actor.parameters()]
    model.actor.zero_grad()
    better = advantages > 0
    (-(0.5 * advantages[better] * taken_log_prob[better]).sum() / 8).backward(retain_graph=True)
    th.manual_seed(1)
    plain_loss = actor_loss(*args)[0]
    plain_loss.backward()
    for grad, param in zip(with_term, model.actor.parameters(), strict=True):
        assert th.allclose(grad, param.grad, atol=1e-5)


@pytest.mark.parametrize("update_precision", ["float32", "bfloat16"])
def test_run_with_self_imitation(update_precision):
    env = make_vec_env("Pendulum-v1", n_envs=4, seed=0)
    policy_kwargs = dict(net_arch=[16, 16], critic_layer_norm=True, n_bins=21, actor_q_reduction="mean")
    model = CGAC(
        "MlpPolicy", env, self_imitation_coef=1.0, policy_kwargs=policy_kwargs, update_precision=update_precision, seed=0
    )
    model.learn(400)
    assert "train/self_imitation_fraction" in model.logger.name_to_value
    assert all(th.isfinite(p).all() for p in model.policy.parameters())


def test_run_with_self_imitation_dict_observations():
    env = make_vec_env(PrivilegedEnv, n_envs=4, seed=0)
    model = CGAC("MultiInputPolicy", env, self_imitation_coef=1.0, policy_kwargs=dict(net_arch=[16, 16], **ASYMMETRIC), seed=0)
    model.learn(400)
    assert model._n_updates > 0 and "train/self_imitation_advantage" in model.logger.name_to_value


def test_save_load_keeps_self_imitation_coef(tmp_path):
    model = make_model(self_imitation_coef=0.5)
    model.save(tmp_path / "model.zip")
    assert CGAC.load(tmp_path / "model.zip").self_imitation_coef == 0.5
    assert make_model().self_imitation_coef == 0.0


@pytest.mark.parametrize("coef", [-1.0, float("nan"), "1", True])
def test_bad_self_imitation_coef(coef):
    with pytest.raises(ValueError, match="self_imitation_coef"):
        make_model(self_imitation_coef=coef)
