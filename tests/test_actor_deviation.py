"""The actor-deviation penalty: actor-critic PQN's trust region of the trained actor around the averaged actor."""

import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_cgac import CGAC
from sb3_cgac.losses import action_deviation_penalty, actor_loss


def make_model(**kwargs) -> CGAC:
    env = make_vec_env("Pendulum-v1", n_envs=4, seed=0)
    return CGAC("MlpPolicy", env, policy_kwargs=dict(net_arch=[16, 16]), n_steps=4, buffer_window=16, seed=0, **kwargs)


def test_penalty_is_zero_within_the_threshold_and_huber_beyond():
    anchor = th.zeros(3, 2)
    actions = th.tensor([[0.05, -0.05], [0.5, 0.3], [2.0, 0.0]])
    penalty = action_deviation_penalty(actions, anchor, threshold=0.1)
    assert penalty[0] == 0.0  # mean |difference| 0.05 < 0.1
    assert th.isclose(penalty[1], th.tensor((0.5 * 0.5**2 + 0.5 * 0.3**2) / 2))
    assert th.isclose(penalty[2], th.tensor((2.0 - 0.5) / 2))  # Huber: linear beyond 1


def test_penalty_pulls_towards_the_anchor():
    actions = th.tensor([[0.6, -0.4]], requires_grad=True)
    action_deviation_penalty(actions, th.zeros(1, 2), threshold=0.0).sum().backward()
    assert actions.grad is not None
    assert (actions.grad * actions.detach() > 0).all()  # gradient descent moves each action back towards 0


def test_actor_loss_with_an_identical_anchor_is_unchanged():
    model = make_model()
    obs, weights = th.randn(8, 3), th.ones(8)
    args = (model.actor, model.critic, obs, weights, weights.sum(), th.tensor(0.1))
    th.manual_seed(1)
    plain, _ = actor_loss(*args)
    th.manual_seed(1)
    # The averaged actor starts as a copy of the trained one: no deviation, no penalty
    anchored, _ = actor_loss(*args, anchor=model.actor_avg, deviation_coef=50.0, deviation_threshold=0.0)
    assert th.allclose(plain, anchored)


def deviation(model: CGAC) -> float:
    obs = th.as_tensor(model.rollout_buffer.observations).reshape(-1, 3)[:256]
    with th.no_grad():
        trained = th.tanh(model.actor.get_action_dist_params(obs)[0])
        averaged = th.tanh(model.actor_avg.get_action_dist_params(obs)[0])
    return (trained - averaged).abs().mean().item()


def test_the_penalty_holds_the_actor_near_the_averaged_actor():
    # policy_tau 0.01: the averaged actor lags far behind; with the penalty the trained actor stays near it
    free = make_model(policy_tau=0.01, learning_rate=3e-3).learn(1_000)
    held = make_model(policy_tau=0.01, learning_rate=3e-3, actor_deviation_coef=1e3, actor_deviation_threshold=0.0)
    held.learn(1_000)
    assert deviation(held) < 0.5 * deviation(free), (deviation(held), deviation(free))


def test_save_load_keeps_the_penalty(tmp_path):
    model = make_model(actor_deviation_coef=50.0, actor_deviation_threshold=0.2).learn(64)
    model.save(tmp_path / "model.zip")
    loaded = CGAC.load(tmp_path / "model.zip")
    assert (loaded.actor_deviation_coef, loaded.actor_deviation_threshold) == (50.0, 0.2)
    loaded.set_env(make_vec_env("Pendulum-v1", n_envs=4, seed=1))
    loaded.learn(64)


@pytest.mark.parametrize("kwargs", [dict(actor_deviation_coef=-1.0), dict(actor_deviation_threshold=float("nan"))])
def test_bad_penalty_arguments(kwargs):
    name = next(iter(kwargs))
    with pytest.raises(ValueError, match=name):
        make_model(**kwargs)
