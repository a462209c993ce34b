"""MuJoCo Playground's tasks as envpool's C++ ports (envpool 1.2.5 and later): episode contract, episode statistics."""

import csv
import subprocess
import sys

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.logger import configure

from sb3_cgac import CGAC
from sb3_cgac.collection import vec_env_step
from sb3_cgac.vec_env import EnvPoolVecEnv, episode_metrics

envpool = pytest.importorskip("envpool")

# task -> the actor's keys of its Dict observation (None: a Box observation)
TASKS = {
    "Go1JoystickFlatTerrain-v1": ["state"],
    "G1JoystickFlatTerrain-v1": ["state"],
    "MuJoCoPlayground/LeapCubeReorient-v1": ["state"],
    "MuJoCoPlayground/PandaPickCube-v1": None,
}


def require(task: str) -> None:
    if task not in envpool.list_all_envs():
        pytest.skip(f"envpool {envpool.__version__} has no {task} (envpool 1.2.5 and later do)")


def rows(obs, idx):
    return {key: value[idx] for key, value in obs.items()} if isinstance(obs, dict) else obs[idx]


def assert_obs_equal(actual, expected) -> None:
    if isinstance(expected, dict):
        assert set(actual) == set(expected)
        for key in expected:
            np.testing.assert_allclose(actual[key], expected[key], rtol=1e-6, atol=1e-6)
    else:
        np.testing.assert_allclose(actual, expected, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("task", list(TASKS))
def test_episode_contract_and_statistics(task):
    """
    The adapter against envpool's own pool, stepped with the same seed and actions through every env's first
    episode (random actions: falls terminate Go1 and G1, time limits end most of the others' episodes): the
    rewards, the real last observation of both kinds of ends, the truncation flag that CGAC bootstraps on (and
    only on), and the episode's return and reward-component sums in ``info["episode"]``.
    """
    require(task)
    n_envs, limit = 6, 60
    vec_env = EnvPoolVecEnv(task, n_envs, seed=3, num_threads=1, max_episode_steps=limit)
    raw = envpool.make_gymnasium(task, num_envs=n_envs, seed=3, num_threads=1, max_episode_steps=limit)
    obs = vec_env.reset()
    raw_obs, raw_infos = raw.reset()
    assert_obs_equal(obs, raw_obs)
    components = sorted(key for key in raw_infos if key.startswith("reward_"))
    assert components, f"{task} reports no reward components"
    rng = np.random.default_rng(0)
    first_episode = np.ones(n_envs, dtype=bool)
    returns, sums = np.zeros(n_envs), {key: np.zeros(n_envs) for key in components}
    ends = {"terminated": 0, "truncated": 0}
    for _ in range(limit):
        actions = rng.uniform(-1, 1, (n_envs, *vec_env.action_space.shape)).astype(np.float32)
        obs, rewards, dones, infos = vec_env.step(actions)
        raw_obs, raw_rewards, raw_terminated, raw_truncated, raw_infos = raw.step(actions)
        step = vec_env_step(obs, rewards, dones, infos, th.device("cpu"))
        terminated, truncated = step.terminated.numpy(), step.truncated.numpy()
        returns += raw_rewards
        for key in components:
            sums[key] += raw_infos[key]
        for idx in np.flatnonzero(first_episode):
            assert rewards[idx] == pytest.approx(raw_rewards[idx], rel=1e-5, abs=1e-6)
            if not (raw_terminated[idx] or raw_truncated[idx]):
                assert not dones[idx]
                assert_obs_equal(rows(obs, idx), rows(raw_obs, idx))
                continue
            info = infos[idx]
            assert dones[idx]
            assert_obs_equal(info["terminal_observation"], rows(raw_obs, idx))
            time_limit = bool(raw_truncated[idx] and not raw_terminated[idx])
            assert info["TimeLimit.truncated"] == time_limit == truncated[idx] != terminated[idx]
            if time_limit:  # CGAC's value target bootstraps from this observation
                assert step.final_observations is not None
                got = rows(step.final_observations, idx)
                got = {key: value.numpy() for key, value in got.items()} if isinstance(got, dict) else got.numpy()
                assert_obs_equal(got, rows(raw_obs, idx))
            episode = info["episode"]
            assert episode["l"] == raw_infos["elapsed_step"][idx]
            assert episode["r"] == pytest.approx(returns[idx], rel=1e-4, abs=1e-4)
            for key in components:
                assert episode[key] == pytest.approx(sums[key][idx], rel=1e-6, abs=1e-9)
            ends["truncated" if time_limit else "terminated"] += 1
            first_episode[idx] = False
    assert not first_episode.any()
    # Both kinds of ends are exercised: falls terminate Go1 and G1, time limits cut LeapCube and Panda
    assert ends["terminated" if task.startswith(("Go1", "G1")) else "truncated"] > 0


def test_episode_info_aggregations():
    """Explicit aggregations: LeapCube's success counter at the episode's end, the mean and max of a component."""
    task = "MuJoCoPlayground/LeapCubeReorient-v1"
    require(task)
    episode_info = {"success_count": "last", "reward_orientation": "mean", "reward_position": "max"}
    vec_env = EnvPoolVecEnv(task, 2, seed=0, num_threads=1, max_episode_steps=20, episode_info=episode_info)
    raw = envpool.make_gymnasium(task, num_envs=2, seed=0, num_threads=1, max_episode_steps=20)
    vec_env.reset()
    raw.reset()
    seen = {"reward_orientation": [], "reward_position": []}
    rng = np.random.default_rng(1)
    for _ in range(20):
        actions = rng.uniform(-0.2, 0.2, (2, *vec_env.action_space.shape)).astype(np.float32)
        _, _, dones, infos = vec_env.step(actions)
        *_, raw_infos = raw.step(actions)
        for key in seen:
            seen[key].append(raw_infos[key][0])
        if dones[0]:
            break
    episode = infos[0]["episode"]
    assert set(episode) == {"r", "l", "t", *episode_info}
    assert episode["success_count"] == raw_infos["success_count"][0]
    assert episode["reward_orientation"] == pytest.approx(np.mean(seen["reward_orientation"]))
    assert episode["reward_position"] == pytest.approx(np.max(seen["reward_position"]))
    with pytest.raises(ValueError, match="unknown aggregation"):
        EnvPoolVecEnv(task, 2, episode_info={"success_count": "median"})


@pytest.mark.parametrize("task", list(TASKS))
def test_cgac_logs_episode_statistics(task, tmp_path):
    """A short CGAC run (the asymmetric actor on ``state`` for the Dict tasks): the reward components reach the logger."""
    require(task)
    env = EnvPoolVecEnv(task, 8, seed=0, num_threads=1, max_episode_steps=30)
    actor_keys = TASKS[task]
    policy_kwargs: dict = dict(net_arch=[32, 32])
    if actor_keys is not None:
        policy_kwargs.update(actor_keys=actor_keys, critic_keys=["privileged_state"])
    model = CGAC("MultiInputPolicy" if actor_keys else "MlpPolicy", env, policy_kwargs=policy_kwargs, batch_size=64, seed=0)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(8 * 96, log_interval=1)
    metrics = episode_metrics(model.ep_info_buffer)
    assert metrics and all(key.startswith("reward_") or key in ("success_count", "out_of_bounds") for key in metrics)
    with open(tmp_path / "progress.csv") as file:
        logged = list(csv.DictReader(file))[-1]
    for key, value in metrics.items():
        assert float(logged[f"rollout/ep_{key}_mean"]) == pytest.approx(value, rel=1e-6)


def test_compare_cgac_rsl_ppo_and_ppo_with_metrics(tmp_path):
    """
    ``sb3_cgac.compare`` runs CGAC, rsl_rl's PPO and SB3's parallel PPO on a Playground task with the entries'
    settings (here at 8 envs), and records a reward component per evaluation and in the summary.
    """
    task = "MuJoCoPlayground/PandaPickCube-v1"
    require(task)
    pytest.importorskip("rsl_rl")
    import yaml

    from sb3_cgac.zoo import HYPERPARAMS_DIR

    conf = tmp_path / "conf"
    conf.mkdir()
    for name, few in (
        ("cgac", {"n_envs": 8, "batch_size": 64}),
        ("rsl_ppo", {"n_envs": 8}),
        ("ppo_parallel", {"n_envs": 8, "batch_size": 48}),
    ):
        entry = yaml.safe_load((HYPERPARAMS_DIR / f"{name}.yml").read_text())[task]
        (conf / f"{name}.yml").write_text(yaml.safe_dump({task: {**entry, **few}}))
    out = tmp_path / "cmp"
    result = subprocess.run(
        [sys.executable, "-m", "sb3_cgac.compare", "--env", task, "--runs", "cgac", "rsl_ppo", "ppo_parallel", "--seeds", "1",
         "--steps", "384", "--eval-every", "0.5", "--eval-episodes", "2", "--eval-envs", "2", "--backend", "envpool",
         "--jobs", "2", "--metrics", "reward_box_target", "reward_gripper_box", "--conf-dir", str(conf), "--out", str(out)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    rows = list(csv.DictReader((out / "evaluations.csv").read_text().splitlines()))
    assert {row["run"] for row in rows} == {"cgac", "rsl_ppo", "ppo_parallel"}
    # Panda's episodes last 150 steps: every evaluation saw whole episodes and their reward components
    assert all(float(row["mean_length"]) == 150 and float(row["reward_gripper_box"]) > 0 for row in rows)
    table = (out / "summary.md").read_text()
    assert "final reward_box_target |" in table and "| rsl_ppo | 1 |" in table
    train_stats = list(csv.DictReader((out / "runs" / "rsl_ppo_seed0_train.csv").read_text().splitlines()))
    assert "value_loss" in train_stats[-1]
