"""The critic options: LayerNorm, categorical (HL-Gauss) heads on a symlog support, and how the actor reads the critics."""

import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from torch import nn

from sb3_cgac import CGAC
from sb3_cgac.critics import SYMLOG_LIMIT, HistogramSupport, symexp, symlog
from sb3_cgac.losses import actor_loss, critic_loss

OPTIONS = dict(critic_layer_norm=True, n_bins=51, actor_q_reduction="mean")


def make_model(**policy_kwargs) -> CGAC:
    env = make_vec_env("Pendulum-v1", n_envs=4, seed=0)
    return CGAC("MlpPolicy", env, policy_kwargs=dict(net_arch=[16, 16], **policy_kwargs), seed=0)


def test_symlog_round_trip():
    x = th.tensor([-1e4, -3.0, -0.5, 0.0, 0.2, 7.0, 2e3])
    assert th.allclose(symexp(symlog(x)), x, rtol=1e-5)


@pytest.mark.parametrize("target", [-5000.0, -40.0, -1.0, 0.0, 0.3, 12.0, 600.0, 15000.0])
def test_hl_gauss_expected_value_is_the_target(target):
    # The HL-Gauss distribution of a target, read back as a Q-value, gives the target (up to the bins' rounding)
    support = HistogramSupport(101)
    probs = support.target_probabilities(th.tensor([target]))
    assert probs.shape == (1, 101)
    assert th.allclose(probs.sum(-1), th.ones(1))
    q_value = support.expected_value(probs.log()).item()
    assert abs(symlog(th.tensor(q_value)) - symlog(th.tensor(target))) < 0.01


def test_hl_gauss_targets_beyond_the_support_are_clamped():
    support = HistogramSupport(101)
    top = support.expected_value(support.target_probabilities(th.tensor([1e12])).log()).item()
    # Half the Gaussian's mass is cut at the limit: the read-back value lies a little below symexp(SYMLOG_LIMIT)
    assert symexp(th.tensor(SYMLOG_LIMIT - 0.2)).item() < top <= symexp(th.tensor(SYMLOG_LIMIT)).item()


def test_layer_norm_and_bins_shape_the_networks():
    model = make_model(critic_layer_norm=True, n_bins=21)
    for critic in (model.critic, model.critic_target):
        for q_net in critic.q_networks:
            assert sum(isinstance(layer, nn.LayerNorm) for layer in q_net) == 2
            assert q_net[-1].out_features == 21
    obs = th.randn(5, 3)
    actions = th.rand(5, 1) * 2 - 1
    assert model.critic.q_outputs(obs, actions).shape == (2, 5, 21)
    assert model.critic.q_values(obs, actions).shape == (2, 5)
    assert model.policy.target_q_value(obs, actions).shape == (5,)


def test_default_critics_unchanged():
    # No option: SB3's networks, one output each, no norm and no support
    model = make_model()
    assert model.critic.support is None
    for q_net in model.critic.q_networks:
        assert q_net[-1].out_features == 1
        assert not any(isinstance(layer, nn.LayerNorm) for layer in q_net)


def test_categorical_critic_fits_targets():
    # Cross-entropy to the HL-Gauss targets drives the critics' Q-values to the targets (as regression would)
    th.manual_seed(0)
    critic = make_model(n_bins=51, critic_layer_norm=True).critic
    obs, actions = th.randn(64, 3), th.rand(64, 1) * 2 - 1
    returns = 100.0 * obs[:, 0] + 20.0 * actions[:, 0] - 50.0
    weights = th.ones(64)
    optimizer = th.optim.Adam(critic.parameters(), lr=3e-3)
    for _ in range(600):
        loss, _ = critic_loss(critic, obs, actions, returns, weights, weights.sum())
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    q_values = critic.q_values(obs, actions).detach()
    assert (q_values - returns).abs().mean() < 5.0, (q_values - returns).abs().mean()


@pytest.mark.parametrize("reduction", ["min", "mean"])
def test_actor_q_reduction(reduction):
    model = make_model(actor_q_reduction=reduction)
    obs = th.randn(8, 3)
    weights = th.ones(8)
    th.manual_seed(1)
    loss, log_prob = actor_loss(model.actor, model.critic, obs, weights, weights.sum(), th.tensor(0.0), q_reduction=reduction)
    th.manual_seed(1)
    actions, _ = model.actor.action_log_prob(obs)
    q_values = model.critic.q_values(obs, actions)
    expected = q_values.min(dim=0).values if reduction == "min" else q_values.mean(dim=0)
    assert th.allclose(loss, -expected.mean())
    assert log_prob.shape == (8,)


def test_one_critic():
    # A single critic: the targets and the actor read it as it is (no minimum of two)
    model = make_model(n_critics=1, **OPTIONS)
    assert len(model.critic.q_networks) == len(model.critic_target.q_networks) == 1
    obs, actions = th.randn(6, 3), th.rand(6, 1) * 2 - 1
    assert th.allclose(model.policy.target_q_value(obs, actions), model.critic_target.q_values(obs, actions)[0])
    model.learn(400)
    assert model._n_updates > 0
    assert all(th.isfinite(p).all() for p in model.policy.parameters())


@pytest.mark.parametrize("update_precision", ["float32", "bfloat16"])
def test_run_with_every_option(update_precision):
    env = make_vec_env("Pendulum-v1", n_envs=4, seed=0)
    policy_kwargs = dict(net_arch=[16, 16], **OPTIONS)
    model = CGAC("MlpPolicy", env, policy_kwargs=policy_kwargs, update_precision=update_precision, seed=0)
    model.learn(400)
    assert model._n_updates > 0
    assert all(th.isfinite(p).all() for p in model.policy.parameters())


def test_save_load_keeps_the_options(tmp_path):
    model = make_model(**OPTIONS)
    model.learn(200)
    model.save(tmp_path / "model.zip")
    loaded = CGAC.load(tmp_path / "model.zip")
    assert loaded.policy.actor_q_reduction == "mean"
    assert loaded.critic.support is not None and loaded.critic.layer_norm
    obs = th.randn(5, 3)
    actions = th.rand(5, 1) * 2 - 1
    assert th.allclose(loaded.critic.q_values(obs, actions), model.critic.q_values(obs, actions))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(n_bins=1), "n_bins"),
        (dict(n_bins=50.5), "n_bins"),
        (dict(actor_q_reduction="max"), "actor_q_reduction"),
        (dict(n_critics=0), "n_critics"),
        (dict(n_critics=1.0), "n_critics"),
    ],
)
def test_bad_critic_options(kwargs, message):
    with pytest.raises(ValueError, match=message):
        make_model(**kwargs)
