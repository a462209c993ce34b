import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.env_checker import check_env
from stable_baselines3.common.env_util import make_vec_env

from sb3_cgac import CGAC
from sb3_cgac.buffers import CGACRolloutBuffer, _linear_recurrence
from sb3_cgac.collection import EnvStep, split_episode_ends, vec_env_step

GAMMA, LAMBDA = 0.9, 0.8
OBS_SPACE = spaces.Box(-np.inf, np.inf, (1,), np.float32)
ACTION_SPACE = spaces.Box(-1, 1, (1,), np.float32)


def fake_target_q(obs: th.Tensor, actions: th.Tensor) -> th.Tensor:
    # Qbar(s, a) = s + a: every value of the example is known by hand
    return obs[:, 0] + actions[:, 0]


def literal_q_gae(rewards, next_values, terminated, truncated, valid, horizon=None):
    """
    Eq. 9-10 written as the literal sum, one env: Y_t = sum_k (g lam)^k delta_{t+k} with
    delta_t = r_t + g m_t Qbar_{t+1} (first term) and delta_{t+k} = r_{t+k} + g m Qbar_{t+k+1} - Qbar_{t+k},
    cut at episode ends, at an excluded next transition, at the window end and after `horizon` terms.
    """
    size = len(rewards)
    targets = []
    for t in range(size):
        total, k = 0.0, 0
        while True:
            j = t + k
            delta = rewards[j] + GAMMA * (not terminated[j]) * next_values[j]
            if k > 0:
                delta -= next_values[j - 1]
            total += (GAMMA * LAMBDA) ** k * delta
            k += 1
            ended = terminated[j] or truncated[j] or j + 1 >= size or not valid[j + 1]
            if ended or (horizon is not None and k >= horizon):
                break
        targets.append(total)
    return np.array(targets)


def env_step(rewards, terminated, truncated, next_obs, obs_ok=None, final_obs=None):
    """An EnvStep of tensors (as ``sb3_cgac.collection`` gives the window), from lists or arrays."""
    n_envs = len(rewards)
    ok = th.ones(n_envs, dtype=th.bool) if obs_ok is None else th.as_tensor(np.asarray(obs_ok))
    final_ok = None if final_obs is None else th.ones(n_envs, dtype=th.bool)
    return EnvStep(
        th.as_tensor(np.asarray(next_obs, dtype=np.float32)),
        ok,
        th.as_tensor(np.asarray(rewards, dtype=np.float32)),
        th.as_tensor(np.asarray(terminated, dtype=bool)),
        th.as_tensor(np.asarray(truncated, dtype=bool)),
        None if final_obs is None else th.as_tensor(np.asarray(final_obs, dtype=np.float32)),
        final_ok,
        [{}] * n_envs,
    )


def fill_buffer(buffer, steps, terminal_value=None):
    """Add steps of a single env: (obs, action, reward, terminated, truncated, next_action)."""
    buffer.set_current_obs(th.tensor([[steps[0][0]]], dtype=th.float32), th.tensor([True]))
    for i, (_, action, reward, terminated, truncated, next_action) in enumerate(steps):
        next_obs = steps[i + 1][0] if i + 1 < len(steps) else 100.0
        final = [[terminal_value]] if truncated else None
        step = env_step([reward], [terminated], [truncated], [[next_obs]], final_obs=final)
        buffer.add(th.tensor([[action]]), step, th.tensor([[next_action]]))


# (obs, action, reward, terminated, truncated, next_action); the next observation is the following row's obs
STEPS = [
    (0.0, 0.1, 1.0, False, False, 0.5),
    (1.0, 0.2, 2.0, False, False, 0.25),
    (2.0, 0.3, -1.0, True, False, 0.0),  # termination: no bootstrap
    (10.0, 0.4, 0.5, False, False, 0.125),  # after reset
    (11.0, 0.5, 1.5, False, True, 0.75),  # time limit: bootstrap from the terminal obs (7.0)
    (20.0, 0.6, 3.0, False, False, 0.0),
    (21.0, 0.7, 1.0, False, False, 0.5),  # newest: next obs is the current obs (100.0)
]
# Qbar_{t+1} = next obs + next action, by hand
EXPECTED_NEXT_VALUES = [1.5, 2.25, 10.0, 11.125, 7.75, 21.0, 100.5]


def test_next_values_and_targets():
    buffer = CGACRolloutBuffer(8, OBS_SPACE, ACTION_SPACE, device="cpu", gamma=GAMMA, gae_lambda=LAMBDA)
    fill_buffer(buffer, STEPS, terminal_value=7.0)
    buffer.compute_returns(fake_target_q)
    size = len(STEPS)
    assert np.allclose(buffer.next_values[:size, 0].numpy(), EXPECTED_NEXT_VALUES)

    rewards = [s[2] for s in STEPS]
    terminated = [s[3] for s in STEPS]
    truncated = [s[4] for s in STEPS]
    expected = literal_q_gae(rewards, EXPECTED_NEXT_VALUES, terminated, truncated, [True] * size)
    assert np.allclose(buffer.returns[:size, 0].numpy(), expected, atol=1e-5)
    # Spot checks of the hand computation
    assert buffer.returns[2, 0].item() == pytest.approx(-1.0)  # terminal: reward only
    assert buffer.returns[4, 0].item() == pytest.approx(1.5 + GAMMA * 7.75)  # truncation: one-step bootstrap
    assert buffer.returns[6, 0].item() == pytest.approx(1.0 + GAMMA * 100.5)  # newest: cut at the window end
    y5 = 3.0 + GAMMA * 21.0 + GAMMA * LAMBDA * (1.0 + GAMMA * 100.5 - 21.0)
    assert buffer.returns[5, 0].item() == pytest.approx(y5)
    assert buffer.weights[:size].eq(1).all()


@pytest.mark.parametrize("horizon", [1, 2, 3])
def test_horizon_cut(horizon):
    buffer = CGACRolloutBuffer(8, OBS_SPACE, ACTION_SPACE, device="cpu", gamma=GAMMA, gae_lambda=LAMBDA, gae_horizon=horizon)
    # A long episode so that the horizon, not the episode end, cuts the sums
    steps = [(float(i), 0.0, float(i % 3) - 0.5, False, False, 0.1 * i) for i in range(8)]
    fill_buffer(buffer, steps)
    buffer.compute_returns(fake_target_q)
    next_values = [steps[i + 1][0] + steps[i][5] if i + 1 < 8 else 100.0 + steps[i][5] for i in range(8)]
    expected = literal_q_gae([s[2] for s in steps], next_values, [False] * 8, [False] * 8, [True] * 8, horizon)
    assert np.allclose(buffer.returns[:, 0].numpy(), expected, atol=1e-5)
    if horizon == 1:
        assert np.allclose(buffer.returns[:, 0].numpy(), np.array([s[2] for s in steps]) + GAMMA * np.array(next_values))


def test_ring_wraps_and_computes_only_new_values():
    window = 4
    buffer = CGACRolloutBuffer(window, OBS_SPACE, ACTION_SPACE, device="cpu", gamma=GAMMA, gae_lambda=LAMBDA)
    steps = [(float(i), 0.0, 1.0 + i, False, False, 0.0) for i in range(7)]
    calls = []

    def counting_q(obs, actions):
        calls.append(len(obs))
        return fake_target_q(obs, actions)

    fill_buffer(buffer, steps[:3])
    buffer.compute_returns(counting_q)
    buffer.set_current_obs(th.tensor([[3.0]]), th.tensor([True]))
    for i in range(3, 7):
        next_obs = steps[i + 1][0] if i + 1 < 7 else 100.0
        buffer.add(th.zeros(1, 1), env_step([steps[i][2]], [False], [False], [[next_obs]]), th.zeros(1, 1))
    buffer.compute_returns(counting_q)
    assert calls == [3, 4]  # Qbar is evaluated once per step
    assert buffer.size == window and buffer.pos == 7 % window
    # Chronological order of the window: steps 3..6
    order = [(buffer.pos + k) % window for k in range(window)]
    window_rewards = [s[2] for s in steps[3:]]
    next_values = [4.0, 5.0, 6.0, 100.0]
    expected = literal_q_gae(window_rewards, next_values, [False] * 4, [False] * 4, [True] * 4)
    assert np.allclose(buffer.returns[order, 0].numpy(), expected, atol=1e-5)


@pytest.mark.parametrize("n_steps", [1, 2, 3, 5, 8, 32, 37])
def test_linear_recurrence_matches_the_step_loop(n_steps):
    # The scan that computes the targets against y_t = a_t + b_t y_{t+1} step by step, with cut traces (b = 0)
    generator = th.Generator().manual_seed(n_steps)
    offsets = th.randn(n_steps, 6, generator=generator, dtype=th.float64)
    decays = th.rand(n_steps, 6, generator=generator, dtype=th.float64) * (th.rand(n_steps, 6, generator=generator) > 0.2)
    expected = offsets.clone()
    for step in range(n_steps - 2, -1, -1):
        expected[step] += decays[step] * expected[step + 1]
    assert th.allclose(_linear_recurrence(offsets, decays), expected, rtol=1e-12, atol=1e-12)


def test_targets_of_a_window_of_many_envs():
    # 37 steps (not a power of two) of 5 envs with terminations and truncations, against the literal sum per env
    window, n_envs = 37, 5
    rng = np.random.default_rng(0)
    buffer = CGACRolloutBuffer(window, OBS_SPACE, ACTION_SPACE, device="cpu", n_envs=n_envs, gamma=GAMMA, gae_lambda=LAMBDA)
    obs = rng.normal(size=(window + 1, n_envs, 1)).astype(np.float32)
    next_actions = rng.uniform(-1, 1, size=(window, n_envs, 1)).astype(np.float32)
    rewards = rng.normal(size=(window, n_envs)).astype(np.float32)
    terminated, truncated = rng.random((window, n_envs)) < 0.1, rng.random((window, n_envs)) < 0.05
    truncated &= ~terminated
    assert terminated.sum() >= 5 and truncated.sum() >= 5, "the check needs episode ends of both kinds"
    buffer.set_current_obs(th.from_numpy(obs[0]), th.ones(n_envs, dtype=th.bool))
    for t in range(window):
        # The time-limited envs bootstrap from a terminal observation of 7.0 (the other rows of the final
        # observations are arbitrary: -50, never read)
        final = np.where(truncated[t][:, None], 7.0, -50.0) if truncated[t].any() else None
        step = env_step(rewards[t], terminated[t], truncated[t], obs[t + 1], final_obs=final)
        buffer.add(th.zeros(n_envs, 1), step, th.from_numpy(next_actions[t]))
    buffer.compute_returns(fake_target_q)
    next_obs = np.where(truncated[..., None], 7.0, obs[1:])
    next_values = (next_obs + next_actions)[..., 0]
    for env in range(n_envs):
        expected = literal_q_gae(rewards[:, env], next_values[:, env], terminated[:, env], truncated[:, env], [True] * window)
        assert np.allclose(buffer.returns[:, env].numpy(), expected, atol=1e-5)


def test_nonfinite_transitions_are_excluded():
    buffer = CGACRolloutBuffer(8, OBS_SPACE, ACTION_SPACE, device="cpu", gamma=GAMMA, gae_lambda=LAMBDA)
    buffer.set_current_obs(th.zeros(1, 1), th.tensor([True]))
    obs_ok = [False, True, True, True, True]  # the observation reached by step 0 was NaN (sanitized to 0)
    rewards = [1.0, 1.0, np.nan, 1.0, 1.0]
    for i in range(5):
        buffer.add(th.zeros(1, 1), env_step([rewards[i]], [False], [False], [[0.0]], obs_ok=[obs_ok[i]]), th.zeros(1, 1))
    buffer.compute_returns(fake_target_q)
    # step 0: bad next obs; step 1: bad obs; step 2: bad reward; steps 3-4 fine
    assert buffer.weights[:5, 0].tolist() == [0.0, 0.0, 0.0, 1.0, 1.0]
    assert buffer.n_nonfinite == 2
    assert th.isfinite(buffer.returns[:5]).all()
    # The trace of a valid step never runs into an excluded one
    assert buffer.returns[3, 0].item() == pytest.approx(
        literal_q_gae([1.0, 1.0], [0.0, 0.0], [False] * 2, [False] * 2, [True] * 2)[0]
    )


class InfiniteHorizonEnv(gym.Env):
    """Constant observation, reward 1 forever, but episodes are cut by a time limit (like SB3's test_gae)."""

    observation_space = spaces.Box(-1, 1, (2,), np.float32)
    action_space = spaces.Box(-1, 1, (1,), np.float32)

    def __init__(self, n_steps: int = 4):
        super().__init__()
        self.n_steps = n_steps
        self.current_step = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.current_step = 0
        return np.zeros(2, dtype=np.float32), {}

    def step(self, action):
        self.current_step += 1
        return np.zeros(2, dtype=np.float32), 1.0, False, self.current_step >= self.n_steps, {}


def test_split_episode_ends():
    # Env 0 runs on, env 1 terminates, env 2 is cut by its time limit (SB3's info keys)
    dones = np.array([False, True, True])
    infos = [{}, {"terminal_observation": np.ones(2)}, {"TimeLimit.truncated": True, "terminal_observation": np.full(2, 3.0)}]
    terminated, truncated = split_episode_ends(dones, infos)
    assert terminated.tolist() == [False, True, False]
    assert truncated.tolist() == [False, False, True]
    # No episode end: nothing to sort out
    terminated, truncated = split_episode_ends(np.zeros(3, dtype=bool), [{}] * 3)
    assert not terminated.any() and not truncated.any()


def test_vec_env_step_is_tensors():
    # An SB3 VecEnv's step as the window takes it: tensors, the truncated env's real last observation in its row
    obs = np.array([[0.0, 0.0], [1.0, 1.0], [np.nan, 2.0]])
    dones = np.array([False, True, True])
    infos = [{}, {"terminal_observation": np.ones(2)}, {"TimeLimit.truncated": True, "terminal_observation": np.full(2, 3.0)}]
    step = vec_env_step(obs, np.array([1.0, 2.0, 3.0]), dones, infos, th.device("cpu"))
    assert step.rewards.dtype == th.float32 and step.observations.dtype == th.float32
    assert step.terminated.tolist() == [False, True, False] and step.truncated.tolist() == [False, False, True]
    assert step.dones.tolist() == dones.tolist()
    assert step.obs_ok.tolist() == [True, True, False]
    assert step.final_observations is not None and step.final_ok is not None
    assert th.equal(step.final_observations[2], th.full((2,), 3.0)) and step.final_ok[2]
    assert th.equal(step.bootstrap_observations(), th.tensor([[0.0, 0.0], [1.0, 1.0], [3.0, 3.0]]))
    # No truncation: no final observations to carry
    step = vec_env_step(obs[:2], np.zeros(2), np.array([False, True]), infos[:2], th.device("cpu"))
    assert step.final_observations is None and step.bootstrap_observations() is step.observations
    # A truncation without the real last observation cannot be bootstrapped: a clear error
    with pytest.raises(ValueError, match="terminal_observation"):
        vec_env_step(obs[:1], np.zeros(1), np.array([True]), [{"TimeLimit.truncated": True}], th.device("cpu"))


def test_infinite_horizon_env_is_valid():
    check_env(InfiniteHorizonEnv())


def test_timeout_bootstrap_infinite_horizon():
    """With truncations bootstrapped, Q tends to 1 / (1 - gamma) = 10; treated as terminations it would stay near 3.4."""
    gamma = 0.9
    env = make_vec_env(InfiniteHorizonEnv, n_envs=16, seed=0)
    model = CGAC(
        "MlpPolicy",
        env,
        gamma=gamma,
        learning_rate=3e-3,
        tau=0.1,
        n_steps=4,
        buffer_window=8,
        critic_updates_per_step=4,
        policy_kwargs=dict(net_arch=[32, 32]),
        seed=0,
    )
    model.learn(6000)
    obs = th.zeros(8, 2, device=model.device)
    actions = th.linspace(-0.9, 0.9, 8, device=model.device).reshape(-1, 1)
    with th.no_grad():
        q_values = th.cat(model.critic(obs, actions), dim=1)
    assert q_values.mean().item() == pytest.approx(1 / (1 - gamma), rel=0.1)
