"""The update step's paths: the default float32 path and bfloat16 autocast give the same updates; the critics' loss."""

import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_cgac import CGAC
from sb3_cgac.hyperparameters import resolve_update_precision
from sb3_cgac.losses import q_regression_loss

SMALL = dict(policy_kwargs=dict(net_arch=[32, 32]), seed=0, n_steps=4, buffer_window=8, batch_size=64)


def filled_model(**kwargs) -> CGAC:
    model = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=16, seed=0), **{**SMALL, **kwargs})
    model.learn(16 * 8)  # fills the window
    return model


def one_update(model: CGAC) -> dict[str, th.Tensor]:
    """Critic and actor losses of one update from the model's current state, on a fixed minibatch."""
    th.manual_seed(1)
    minibatch = model.rollout_buffer.sample(64)
    critic_loss = model._critic_update(minibatch)["critic_loss"]
    actor = model._actor_update(th.tensor(-1.0), minibatch)
    return {"critic_loss": critic_loss, "actor_loss": actor["actor_loss"], "entropy": actor["entropy"]}


def test_q_regression_loss():
    returns, weights = th.zeros(4), th.tensor([1.0, 1.0, 1.0, 0.0])
    q_values = th.tensor([[1.0, 1.0, 2.0, 100.0], [1.0, 1.0, 10.0, 7.0]])  # (n_critics, batch)
    # Huber, per critic: 4x the median |delta| (lower median of [0, 1, 1, 2] and [0, 1, 1, 10]: 1) is 4; |delta| = 10 is
    # above it and counts linearly, 2 * 4 * 10 - 4**2 = 64 (the excluded sample has delta = 0)
    assert q_regression_loss(q_values, returns, weights) == pytest.approx((1 + 1 + 4) + (1 + 1 + 64))
    # The squared error everywhere: 10 counts as 100
    assert q_regression_loss(q_values, returns, weights, loss="mse") == pytest.approx((1 + 1 + 4) + (1 + 1 + 100))


def test_critic_loss_option():
    model = filled_model(critic_loss="mse")
    assert model.critic_loss == "mse" and one_update(model)["critic_loss"] > 0
    with pytest.raises(ValueError, match=r"unknown critic_loss 'l1'; choose one of \('huber', 'mse'\)"):
        filled_model(critic_loss="l1")


def test_bfloat16_updates_match_float32():
    reference, bf16 = filled_model(), filled_model(update_precision="bfloat16")
    losses, losses_bf16 = one_update(reference), one_update(bf16)
    for key, value in losses.items():
        # bfloat16 keeps 8 bits of mantissa: about 2-3 significant digits
        assert losses_bf16[key].item() == pytest.approx(value.item(), rel=0.05, abs=0.05), key


def test_bfloat16_q_value_precision():
    # Under bfloat16 autocast the critics' hidden layers run in bfloat16, their output layer in float32: Q-values of
    # hundreds keep their fractional part (bfloat16 alone would round 500.3 to 500)
    model = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=16), policy_kwargs=dict(net_arch=[32, 32]), device="cpu")
    critic = model.critic
    with th.no_grad():
        for param in critic.parameters():
            param.mul_(0.01)
        critic.q_networks[0][-1].bias.add_(500.3)
    obs, actions = th.randn(8, 3), th.rand(8, 1) * 2 - 1
    q_values = critic.q_values(obs, actions)
    with th.autocast("cpu", dtype=th.bfloat16):
        q_values_bf16 = critic.q_values(obs, actions)
    assert q_values_bf16.dtype == th.float32
    th.testing.assert_close(q_values_bf16[0], q_values[0], rtol=0, atol=0.02)
    assert (q_values_bf16[0] - 500).abs().min() > 0.2


@pytest.mark.parametrize("native", [True, False])
def test_auto_precision_follows_the_cpu(native, monkeypatch, tmp_path):
    # "auto" is bfloat16 exactly where the CPU multiplies bfloat16 in hardware, and is resolved again at load time
    monkeypatch.setattr(th.cpu, "_is_avx512_bf16_supported", lambda: native)
    monkeypatch.setattr(th.cpu, "_is_amx_tile_supported", lambda: False)
    expected = th.bfloat16 if native else None
    env = make_vec_env("Pendulum-v1", n_envs=16)
    model = CGAC("MlpPolicy", env, policy_kwargs=dict(net_arch=[8]), update_precision="auto", device="cpu")
    assert model._autocast_dtype is expected
    assert CGAC("MlpPolicy", env, policy_kwargs=dict(net_arch=[8]), device="cpu")._autocast_dtype is None  # default: float32
    assert resolve_update_precision("float32", th.device("cpu")) is None
    assert resolve_update_precision("bfloat16", th.device("cpu")) is th.bfloat16
    assert resolve_update_precision("auto", th.device("cuda")) is None  # no faster on CUDA in eager mode: float32
    model.save(tmp_path / "model")
    monkeypatch.setattr(th.cpu, "_is_avx512_bf16_supported", lambda: not native)
    loaded = CGAC.load(tmp_path / "model", device="cpu")
    assert loaded.update_precision == "auto" and loaded._autocast_dtype is (None if native else th.bfloat16)


def test_auto_precision_without_torch_helpers(monkeypatch):
    # torch.cpu's helpers are private: a torch without them gets float32
    monkeypatch.delattr(th.cpu, "_is_avx512_bf16_supported")
    assert resolve_update_precision("auto", th.device("cpu")) is None


def test_adam_is_fused_by_default():
    model = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=16), **SMALL)
    assert model.actor.optimizer.defaults["fused"] and model.critic.optimizer.defaults["fused"]
    own = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=16), policy_kwargs=dict(optimizer_kwargs=dict(foreach=True)))
    assert not own.critic.optimizer.defaults["fused"] and own.critic.optimizer.defaults["foreach"]
