import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env

from sb3_cgac import CGAC
from sb3_cgac.callbacks import ProgressEntropySchedule, RewardEntropySchedule
from sb3_cgac.hyperparameters import resolve_batch_size, resolve_critic_updates_per_step, resolve_polyak_rates

SMALL = dict(policy_kwargs=dict(net_arch=[16, 16]), seed=0)


class ConstantRewardEnv(gym.Env):
    observation_space = spaces.Box(-1, 1, (2,), np.float32)
    action_space = spaces.Box(-1, 1, (2,), np.float32)

    def __init__(self, reward: float = 4.5):
        super().__init__()
        self.reward = reward

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.steps = 0
        return self.np_random.uniform(-1, 1, 2).astype(np.float32), {}

    def step(self, action):
        self.steps += 1
        return self.np_random.uniform(-1, 1, 2).astype(np.float32), self.reward, False, self.steps >= 50, {}


class RecordAlpha(BaseCallback):
    def __init__(self):
        super().__init__()
        self.alphas: list[float] = []
        self.betas: list[tuple[int, float]] = []

    def _on_step(self) -> bool:
        self.alphas.append(th.exp(self.model.log_ent_coef).item())
        self.betas.append((self.num_timesteps, self.model.target_entropy_beta))
        return True


@pytest.mark.parametrize("monotone", [True, "above_target", False])
def test_alpha_rises_when_entropy_is_below_target(monotone):
    # A target entropy far above what the policy can have (beta = -5: +10 nats for 2 action dims) keeps the entropy
    # below its target: SAC-style tuning raises alpha; the paper's clamp never lets it rise; the default clamp,
    # which only holds while the entropy is at or above its target, lets it rise so that exploration cannot lock
    model = CGAC(
        "MlpPolicy",
        make_vec_env(ConstantRewardEnv, n_envs=8, seed=0),
        ent_coef="auto_0.1",
        target_entropy_beta=-5.0,
        ent_coef_monotone=monotone,
        **SMALL,
    )
    record = RecordAlpha()
    model.learn(1200, callback=record)
    alphas = np.array(record.alphas)
    if monotone is True:
        assert np.all(np.diff(alphas) <= 0)
        assert alphas.max() <= 0.1 + 1e-7
    else:
        assert alphas[-1] > 0.1 * 1.5


@pytest.mark.parametrize("monotone", [True, "above_target"])
def test_alpha_never_rises_while_entropy_is_above_target(monotone):
    # Target entropy far below the policy's (beta = 20): alpha's gradient only asks for decreases; Adam's momentum
    # could still step it up after a sign change, which both clamps forbid
    model = CGAC(
        "MlpPolicy",
        make_vec_env(ConstantRewardEnv, n_envs=8, seed=0),
        target_entropy_beta=20.0,
        ent_coef_monotone=monotone,
        **SMALL,
    )
    record = RecordAlpha()
    model.learn(1200, callback=record)
    assert np.all(np.diff(record.alphas) <= 0)
    assert record.alphas[-1] < 0.1 * 0.9


def test_alpha_clamp_releases_only_below_target():
    """One update by hand: with the entropy above target the clamp holds, below it alpha follows Adam up."""
    model = CGAC("MlpPolicy", make_vec_env(ConstantRewardEnv, n_envs=8, seed=0), **SMALL)
    model.learn(400)
    minibatch = model.rollout_buffer.sample(64)
    # Momentum that pushes log(alpha) up, whatever this batch's gradient says
    model.log_ent_coef.grad = th.tensor([-1e6], device=model.device)
    model.ent_coef_optimizer.step()
    for target_entropy, may_rise in ((-100.0, False), (100.0, True)):
        before = model.log_ent_coef.item()
        model._actor_update(th.tensor(target_entropy), minibatch)
        if may_rise:
            assert model.log_ent_coef.item() > before
        else:
            assert model.log_ent_coef.item() <= before


def test_alpha_decreases_when_entropy_is_above_target():
    model = CGAC("MlpPolicy", make_vec_env(ConstantRewardEnv, n_envs=8, seed=0), target_entropy_beta=5.0, **SMALL)
    model.learn(1200)
    assert th.exp(model.log_ent_coef).item() < 0.1 * 0.9


@pytest.mark.parametrize("reward, expected_beta", [(0.0, 0.2), (4.5, 1.85), (20.0, 3.5)])
def test_reward_schedule(reward, expected_beta):
    """Eq. 13: beta = beta_init + (beta_final - beta_init) * (r_avg - r_init) / (r_peak - r_init), clipped."""
    schedule = RewardEntropySchedule(beta_init=0.2, beta_final=3.5, init_expected_reward=1.5, peak_expected_reward=7.5)
    model = CGAC("MlpPolicy", make_vec_env(ConstantRewardEnv, n_envs=4, seed=0, env_kwargs=dict(reward=reward)), **SMALL)
    model.learn(800, callback=schedule)  # 200 steps: the EMA (0.95) has converged
    assert schedule.reward_average == pytest.approx(reward, abs=1e-3)
    assert model.target_entropy_beta == pytest.approx(expected_beta, abs=1e-3)


def test_progress_schedule():
    schedule = ProgressEntropySchedule(beta_init=0.2, beta_final=3.5, end_fraction=0.5)
    record = RecordAlpha()
    model = CGAC("MlpPolicy", make_vec_env(ConstantRewardEnv, n_envs=4, seed=0), **SMALL)
    model.learn(800, callback=[schedule, record])
    steps, betas = np.array(record.betas).T
    assert np.all(np.diff(betas) >= 0)
    assert betas[0] == pytest.approx(0.2 + 3.3 * 4 / 400, abs=1e-6)
    mid = np.searchsorted(steps, 200)
    assert betas[mid] == pytest.approx(0.2 + 3.3 * 0.5, abs=1e-6)
    assert betas[-1] == pytest.approx(3.5)
    assert np.all(betas[steps >= 400] == pytest.approx(3.5))


def test_progress_schedule_sets_target_entropy():
    model = CGAC("MlpPolicy", make_vec_env(ConstantRewardEnv, n_envs=4, seed=0), **SMALL)
    model.learn(400, callback=ProgressEntropySchedule())
    assert model.target_entropy_beta == pytest.approx(3.5)
    # The next update targets -beta * |A|
    model.train()
    assert model.logger.name_to_value["train/target_entropy"] == pytest.approx(-3.5 * 2)


def snapshot(module: th.nn.Module) -> list[th.Tensor]:
    return [p.detach().clone() for p in module.parameters()]


@pytest.mark.parametrize("tau, policy_tau", [(0.005, 0.001), (0.3, 0.5), (1.0, 1.0)])
def test_polyak_updates(tau, policy_tau):
    env = make_vec_env(ConstantRewardEnv, n_envs=8, seed=0)
    model = CGAC("MlpPolicy", env, critic_updates_per_step=2, tau=tau, policy_tau=policy_tau, **SMALL)
    model.learn(400)
    target_before, avg_before = snapshot(model.critic_target), snapshot(model.actor_avg)
    n_updates = model._n_updates
    model.train()  # 2 critic updates, then 1 actor update and the Polyak updates
    assert model._n_updates == n_updates + 2
    for before, critic, target in zip(target_before, model.critic.parameters(), model.critic_target.parameters(), strict=True):
        assert th.allclose(target, (1 - tau) * before + tau * critic, atol=1e-6)
    for before, actor, avg in zip(avg_before, model.actor.parameters(), model.actor_avg.parameters(), strict=True):
        assert th.allclose(avg, (1 - policy_tau) * before + policy_tau * actor, atol=1e-6)
    if tau == 1.0:
        assert all(th.equal(a, b) for a, b in zip(model.critic.parameters(), model.critic_target.parameters(), strict=True))


def test_rollouts_act_with_the_averaged_actor():
    model = CGAC("MlpPolicy", make_vec_env(ConstantRewardEnv, n_envs=4, seed=0), **SMALL)
    with th.no_grad():
        # Near-deterministic actors with different means: 0 for the trained actor, tanh(0.5) for the averaged one
        for actor, bias in ((model.actor, 0.0), (model.actor_avg, 0.5)):
            actor.mu.weight.zero_()
            actor.mu.bias.fill_(bias)
            actor.log_std.fill_(-15.0)
    model.learn(40)  # 10 steps: the window does not hold a minibatch yet, nothing is trained
    assert model._n_updates == 0
    stored = model.rollout_buffer.actions[: model.rollout_buffer.size]
    assert th.allclose(stored, th.full_like(stored, np.tanh(0.5)), atol=1e-4)
    next_actions = model.rollout_buffer.next_actions[: model.rollout_buffer.size]
    assert th.allclose(next_actions, th.full_like(next_actions, np.tanh(0.5)), atol=1e-4)
    action, _ = model.predict(np.zeros((1, 2), np.float32), deterministic=True)
    assert action == pytest.approx(np.tanh(0.5), abs=1e-5)


CPU, CUDA = th.device("cpu"), th.device("cuda")


@pytest.mark.parametrize(
    "n_envs, critic_updates, policy_delay, tau, policy_tau",
    [
        (64, 2, 128, 0.005, 0.001),  # 4096 new transitions per actor update: the paper's values
        (64, 2, 2, 1 - 0.995**8, 1 - 0.999**8),  # 64 per update: sqrt(4096 / 64) = 8 paper updates' worth
        (16, 4, 4, 1 - 0.995**16, 1 - 0.999**16),  # 16 per update: 16x
    ],
)
def test_gpu_averaging_scales_with_transitions_per_update(n_envs, critic_updates, policy_delay, tau, policy_tau):
    assert resolve_polyak_rates("auto", "auto", n_envs, policy_delay, critic_updates, CUDA) == pytest.approx((tau, policy_tau))
    # Models saved by 0.1.0 (None) keep its rule on every device
    assert resolve_polyak_rates(None, None, n_envs, policy_delay, critic_updates, CPU) == pytest.approx((tau, policy_tau))
    # On a CPU: the MuJoCo entries' rates; given values are used as they are, on every device
    assert resolve_polyak_rates("auto", "auto", n_envs, policy_delay, critic_updates, CPU) == (0.02, 0.05)
    assert resolve_polyak_rates(0.3, 0.2, n_envs, policy_delay, critic_updates, CUDA) == (0.3, 0.2)


@pytest.mark.parametrize(
    "n_envs, batch_size, expected",
    [
        (16, 512, 4),
        (64, 2048, 4),
        (1023, 4096, 4),
        (1023, 64, 4),  # the sampling floor starts at 1024 envs
        (1024, 4096, 2),
        (1500, 4096, 3),
        (2048, 4096, 4),
        (4096, 4096, 8),
        (4096, 8192, 4),
        (16384, 4096, 32),
        (1024, 8192, 2),  # never fewer than the paper's 2
    ],
)
def test_gpu_critic_updates_per_step(n_envs, batch_size, expected):
    """On a GPU: 4 below 1024 envs; from 1024 on, each collected transition sampled 8 times (at least the paper's 2)."""
    updates = resolve_critic_updates_per_step("auto", n_envs, batch_size, CUDA)
    assert updates == expected
    assert resolve_critic_updates_per_step(None, n_envs, batch_size, CPU) == expected  # 0.1.0's rule
    if n_envs >= 1024:
        assert updates * batch_size / n_envs >= 8
        assert updates == 2 or (updates - 1) * batch_size / n_envs < 8, "the smallest count that reaches the floor"
    assert resolve_critic_updates_per_step("auto", n_envs, batch_size, CPU) == 4
    assert resolve_critic_updates_per_step(3, n_envs, batch_size, CUDA) == 3


@pytest.mark.parametrize(
    "n_envs, device, expected",
    [
        (16, CPU, 512),
        (8, CPU, 256),
        (128, CPU, 512),
        (4096, CPU, 512),
        (64, CUDA, 2048),
        (128, CUDA, 4096),
        (4096, CUDA, 4096),
    ],
)
def test_auto_batch_size(n_envs, device, expected):
    """512 on a CPU, the paper's 4096 on a GPU, never more than the window of 32 steps."""
    assert resolve_batch_size("auto", 32, n_envs, device) == expected
    assert resolve_batch_size(100, 32, n_envs, device) == 100


def test_auto_values_are_resolved_on_the_model(tmp_path):
    model = CGAC("MlpPolicy", make_vec_env(ConstantRewardEnv, n_envs=16), **SMALL)
    assert (model.batch_size, model.critic_updates_per_step, model.tau, model.policy_tau) == (512, 4, 0.02, 0.05)
    model.learn(16 * 40)  # the window holds a minibatch of 512 from the 32nd step: 9 iterations of updates
    assert model._n_updates == 9 * 4
    # A saved model keeps the numbers it was trained with, wherever it is loaded
    model.save(tmp_path / "model")
    loaded = CGAC.load(tmp_path / "model", env=make_vec_env(ConstantRewardEnv, n_envs=16))
    assert (loaded.batch_size, loaded.critic_updates_per_step, loaded.tau, loaded.policy_tau) == (512, 4, 0.02, 0.05)
