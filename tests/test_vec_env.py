"""The vec-env adapters against the plain gymnasium envs, stepped with the same seeds and actions."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import VecNormalize

from sb3_cgac import CGAC
from sb3_cgac.vec_env import EnvPoolVecEnv, GymnasiumVecEnv, make_vec_env

envpool = pytest.importorskip("envpool")


class Reference:
    """n plain gymnasium envs with SB3's episode contract written out by hand."""

    def __init__(self, env_id: str, n_envs: int, seed: int | None, **env_kwargs):
        self.envs = [gym.make(env_id, **env_kwargs) for _ in range(n_envs)]
        self.seed = seed

    def reset(self) -> np.ndarray:
        seeds = [None if self.seed is None else self.seed + i for i in range(len(self.envs))]
        return np.stack([env.reset(seed=s)[0] for env, s in zip(self.envs, seeds, strict=True)])

    def step(self, actions: np.ndarray):
        obs, rewards, dones, infos = [], [], [], []
        for env, action in zip(self.envs, actions, strict=True):
            o, r, terminated, truncated, _ = env.step(action)
            info = {}
            if terminated or truncated:
                info = {"terminal_observation": o, "TimeLimit.truncated": truncated and not terminated}
                o, _ = env.reset()
            obs.append(o)
            rewards.append(r)
            dones.append(terminated or truncated)
            infos.append(info)
        return np.stack(obs), np.array(rewards), np.array(dones), infos


def compare(vec_env, reference, n_steps: int, action_scale: float, obs_atol: float, reward_atol: float) -> dict[str, int]:
    """Step both with the same random actions; count episode ends of each kind."""
    rng = np.random.default_rng(0)
    obs, ref_obs = vec_env.reset(), reference.reset()
    np.testing.assert_allclose(obs, ref_obs, atol=obs_atol)
    counts = {"terminated": 0, "truncated": 0}
    returns = np.zeros(vec_env.num_envs)
    for _ in range(n_steps):
        actions = rng.uniform(-action_scale, action_scale, (vec_env.num_envs, *vec_env.action_space.shape))
        obs, rewards, dones, infos = vec_env.step(actions.astype(np.float32))
        ref_obs, ref_rewards, ref_dones, ref_infos = reference.step(actions.astype(np.float32))
        returns += rewards
        np.testing.assert_array_equal(dones, ref_dones)
        np.testing.assert_allclose(rewards, ref_rewards, atol=reward_atol)
        np.testing.assert_allclose(obs, ref_obs, atol=obs_atol)
        for idx in np.flatnonzero(dones):
            info, ref_info = infos[idx], ref_infos[idx]
            np.testing.assert_allclose(info["terminal_observation"], ref_info["terminal_observation"], atol=obs_atol)
            assert info["TimeLimit.truncated"] == ref_info["TimeLimit.truncated"]
            assert info["episode"]["r"] == pytest.approx(returns[idx], abs=1e-3)
            counts["truncated" if info["TimeLimit.truncated"] else "terminated"] += 1
            returns[idx] = 0
    return counts


@pytest.mark.parametrize("backend", ["gymnasium", "gymnasium_async"])
@pytest.mark.parametrize(
    "env_id, env_kwargs",
    [("Hopper-v5", {}), ("Pendulum-v1", dict(max_episode_steps=30))],
)
def test_gymnasium_adapter_matches_gymnasium(backend, env_id, env_kwargs):
    vec_env = make_vec_env(env_id, n_envs=3, backend=backend, seed=7, env_kwargs=env_kwargs, random_first_episode=False)
    counts = compare(vec_env, Reference(env_id, 3, seed=7, **env_kwargs), 150, 1.0, obs_atol=0.0, reward_atol=0.0)
    vec_env.close()
    assert counts["terminated" if env_id == "Hopper-v5" else "truncated"] > 0


def test_gymnasium_adapter_next_step_mode_matches_gymnasium():
    """Gymnasium's default NEXT_STEP autoreset: the adapter resets finished envs at once (reset_mask)."""
    venv = gym.make_vec("Hopper-v5", num_envs=3, vectorization_mode="sync")
    assert venv.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    vec_env = GymnasiumVecEnv(venv)
    vec_env.seed(3)
    counts = compare(vec_env, Reference("Hopper-v5", 3, seed=3), 150, 1.0, obs_atol=0.0, reward_atol=0.0)
    assert counts["terminated"] > 0


@pytest.mark.parametrize("env_id, action_dim", [("HalfCheetah-v5", 6), ("Hopper-v5", 3)])
def test_envpool_matches_gymnasium_physics(env_id, action_dim):
    """
    With the reset noise off, envpool and gymnasium start from the same state, and their MuJoCo physics agree
    to ~1e-12 on these envs (rewards are float32 in envpool). Contact-rich envs (Ant-v5, Humanoid-v5) agree
    in structure but drift apart chaotically after a few steps (about 5e-2 in Ant's observation after 10 steps).
    """
    kwargs = dict(reset_noise_scale=0.0, max_episode_steps=40)
    vec_env = EnvPoolVecEnv(env_id, 3, seed=0, **kwargs)
    counts = compare(vec_env, Reference(env_id, 3, seed=None, **kwargs), 130, 0.5, obs_atol=1e-8, reward_atol=1e-5)
    assert counts["truncated"] > 0
    vec_env.close()


def hopper_healthy(obs: np.ndarray) -> bool:
    """Gymnasium Hopper-v5's rule: z > 0.7, |angle| < 0.2 and every other state entry within +-100."""
    return bool(obs[0] > 0.7 and abs(obs[1]) < 0.2 and np.all(np.abs(obs[1:]) < 100.0))


def test_envpool_episode_structure_with_reset_noise():
    """With reset noise the trajectories cannot be matched, but the rules can: terminal states break gymnasium's
    health rule, every other state satisfies it, and a reset starts near the initial height."""
    vec_env = EnvPoolVecEnv("Hopper-v5", 8, seed=0)
    reference = gym.make("Hopper-v5")
    assert vec_env.observation_space == reference.observation_space
    assert vec_env.action_space == reference.action_space
    rng = np.random.default_rng(0)
    obs = vec_env.reset()
    terminations = 0
    for _ in range(200):
        obs, _, dones, infos = vec_env.step(rng.uniform(-1, 1, (8, 3)).astype(np.float32))
        for idx in range(8):
            if dones[idx]:
                assert not infos[idx]["TimeLimit.truncated"]
                assert not hopper_healthy(infos[idx]["terminal_observation"])
                assert obs[idx][0] == pytest.approx(1.25, abs=0.01)
                terminations += 1
            else:
                assert hopper_healthy(obs[idx])
    assert terminations > 10


def test_envpool_seeding():
    first = EnvPoolVecEnv("HalfCheetah-v5", 4, seed=1)
    first.seed(5)
    again = EnvPoolVecEnv("HalfCheetah-v5", 4, seed=5)
    np.testing.assert_array_equal(first.reset(), again.reset())
    other = EnvPoolVecEnv("HalfCheetah-v5", 4, seed=6)
    assert not np.array_equal(first.reset(), other.reset())


def test_env_method_and_attributes():
    vec_env = make_vec_env("Pendulum-v1", n_envs=3, backend="gymnasium", seed=0)
    assert vec_env.get_attr("spec", indices=[1])[0].id == "Pendulum-v1"
    vec_env.set_attr("custom", 1)
    vec_env.set_attr("custom", 3, indices=[2])
    assert vec_env.get_attr("custom") == [1, 1, 3]
    assert len(vec_env.env_method("get_wrapper_attr", "spec")) == 3
    assert vec_env.env_is_wrapped(Monitor) == [True, True, True]
    pool = make_vec_env("HalfCheetah-v5", n_envs=2, backend="envpool", seed=0)
    assert pool.get_attr("num_envs") == [2, 2]
    with pytest.raises(NotImplementedError, match="C\\+\\+ objects"):
        pool.env_method("render")


def test_sb3_backends_render_mode():
    # As SB3's make_vec_env for an env id: rgb_array unless the caller says otherwise, in every worker
    for backend in ("dummy", "subproc"):
        vec_env = make_vec_env("Pendulum-v1", n_envs=2, backend=backend, seed=0)
        assert vec_env.get_attr("render_mode") == ["rgb_array", "rgb_array"]
        vec_env.close()
    vec_env = make_vec_env("Pendulum-v1", n_envs=2, backend="subproc", env_kwargs={"render_mode": None})
    assert vec_env.get_attr("render_mode") == [None, None]
    vec_env.close()


def test_unknown_backend_and_task():
    with pytest.raises(ValueError, match="Unknown vec-env backend 'ray'"):
        make_vec_env("Pendulum-v1", backend="ray")
    with pytest.raises(ValueError, match="envpool has no task 'NotAnEnv-v0'"):
        EnvPoolVecEnv("NotAnEnv-v0", 2)
    with pytest.raises(TypeError, match=r"wraps a gymnasium\.vector\.VectorEnv"):
        GymnasiumVecEnv(gym.make("Pendulum-v1"))


@pytest.mark.parametrize("backend", ["envpool", "gymnasium"])
def test_cgac_with_vec_normalize_on_adapters(backend):
    env = VecNormalize(make_vec_env("Hopper-v5", n_envs=16, backend=backend, seed=0))
    model = CGAC("MlpPolicy", env, policy_kwargs=dict(net_arch=[32]), seed=0)
    model.learn(2000)
    assert len(model.ep_info_buffer) > 0  # rollout/ep_rew_mean is logged
    mean_return, _ = evaluate_policy(model, env, n_eval_episodes=4, warn=False)
    assert np.isfinite(mean_return)


@pytest.mark.parametrize("backend", ["envpool", "gymnasium", "dummy"])
def test_random_first_episode(backend):
    """Every backend spreads the first resets over the episode length, as time-limit truncations with the
    terminal observation; the cut envs restart from a fresh initial state and later episodes run their full length."""
    env_id, limit = ("Hopper-v5", 30) if backend != "dummy" else ("Pendulum-v1", 200)
    env_kwargs = dict(max_episode_steps=limit) if backend != "dummy" else None
    vec_env = make_vec_env(env_id, n_envs=16, backend=backend, seed=0, env_kwargs=env_kwargs, random_first_episode=True)
    obs = vec_env.reset()
    first, later = {}, []
    lengths = np.zeros(16, dtype=int)
    for _ in range(3 * limit):
        # Zero actions: Hopper stands for more than 30 steps, so only the time limit and the cuts end episodes
        new_obs, _, dones, infos = vec_env.step(np.zeros((16, *vec_env.action_space.shape), np.float32))
        lengths += 1
        for idx in np.flatnonzero(dones):
            assert infos[idx]["TimeLimit.truncated"]
            assert not np.array_equal(infos[idx]["terminal_observation"], new_obs[idx])
            # Cut first episodes are not reported as episodes (rollout/ep_rew_mean), as Monitor does for SB3's VecEnvs
            assert ("episode" in infos[idx]) == (lengths[idx] == limit)
            (later.append(lengths[idx]) if idx in first else first.__setitem__(idx, lengths[idx]))
            lengths[idx] = 0
        obs = new_obs
    assert obs.shape[0] == 16
    cuts = np.array(list(first.values()))
    assert len(cuts) == 16 and cuts.min() >= 1 and cuts.max() <= limit and len(set(cuts.tolist())) >= 8
    assert later and set(later) == {limit}
    vec_env.close()
