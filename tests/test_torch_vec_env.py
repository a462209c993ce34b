"""The torch-native path: TorchVecEnv's episode contract, and CGAC trained through it equal to the NumPy path."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium.vector import AutoresetMode, SyncVectorEnv
from stable_baselines3.common.callbacks import BaseCallback
from toy_envs import ReachEnv  # tests/ is on sys.path under pytest

from sb3_cgac import CGAC
from sb3_cgac.callbacks import RewardEntropySchedule
from sb3_cgac.vec_env import GymnasiumVecEnv, NumpyToTorchVectorEnv, TorchVecEnv, make_vec_env, torch_vec_env


def reach_envs(kind: str, n_envs: int = 6, dict_obs: bool = False, seed: int = 0):
    venv = SyncVectorEnv([lambda: ReachEnv(dict_obs)] * n_envs, autoreset_mode=AutoresetMode.SAME_STEP)
    env = TorchVecEnv(NumpyToTorchVectorEnv(venv)) if kind == "torch" else GymnasiumVecEnv(venv)
    env.seed(seed)
    return env


def rows(obs, idx):
    return {key: value[idx] for key, value in obs.items()} if isinstance(obs, dict) else obs[idx]


def to_numpy(obs):
    return {key: value.numpy() for key, value in obs.items()} if isinstance(obs, dict) else obs.numpy()


def assert_obs_equal(a, b):
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for key in a:
            np.testing.assert_array_equal(np.asarray(a[key]), np.asarray(b[key]))
    else:
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("dict_obs", [False, True])
def test_contract_matches_gymnasium_vec_env(dict_obs):
    # The same vector env through GymnasiumVecEnv (NumPy) and TorchVecEnv: SB3's API step for step, and the
    # tensors of step_tensors on a third copy
    numpy_env, torch_env, tensor_env = (reach_envs(kind, dict_obs=dict_obs) for kind in ("numpy", "torch", "torch"))
    assert_obs_equal(numpy_env.reset(), torch_env.reset())
    tensor_env.reset()
    rng = np.random.default_rng(0)
    ends = {"terminated": 0, "truncated": 0}
    for _ in range(80):
        actions = rng.uniform(-1, 1, (6, 2)).astype(np.float32)
        obs, rewards, dones, infos = numpy_env.step(actions)
        t_obs, t_rewards, t_dones, t_infos = torch_env.step(actions)
        step = tensor_env.step_tensors(th.as_tensor(actions))
        assert_obs_equal(obs, t_obs)
        assert_obs_equal(obs, to_numpy(step.observations))
        np.testing.assert_array_equal(rewards, t_rewards)
        np.testing.assert_array_equal(rewards, step.rewards.numpy())
        np.testing.assert_array_equal(dones, t_dones)
        for idx in range(6):
            truncated = infos[idx].get("TimeLimit.truncated", False)
            assert truncated == t_infos[idx].get("TimeLimit.truncated", False) == bool(step.truncated[idx])
            assert (dones[idx] and not truncated) == bool(step.terminated[idx])
            if dones[idx]:
                ends["truncated" if truncated else "terminated"] += 1
                assert_obs_equal(infos[idx]["terminal_observation"], t_infos[idx]["terminal_observation"])
                assert_obs_equal(infos[idx]["terminal_observation"], rows(to_numpy(step.final_observations), idx))
                assert infos[idx]["episode"]["r"] == pytest.approx(t_infos[idx]["episode"]["r"], rel=1e-6)
                assert infos[idx]["episode"]["l"] == t_infos[idx]["episode"]["l"]
                for key in ("reward_distance", "reward_steps"):  # the last step's, from final_info, counted
                    assert t_infos[idx]["episode"][key] == pytest.approx(infos[idx]["episode"][key], rel=1e-6)
                length = infos[idx]["episode"]["l"]
                assert t_infos[idx]["episode"]["reward_steps"] == length * (length + 1) / 2
                assert t_infos[idx]["episode"]["reward_distance"] == pytest.approx(t_infos[idx]["episode"]["r"], rel=1e-5)
    assert ends["terminated"] > 0 and ends["truncated"] > 0  # both kinds of ends were checked
    episodes = tensor_env.pop_episodes()
    assert len(episodes) == sum(ends.values()) and tensor_env.pop_episodes() == []
    assert all(episode["reward_steps"] == episode["l"] * (episode["l"] + 1) / 2 for episode in episodes)


def test_random_first_episode_cuts_as_gymnasium_vec_env():
    numpy_env = make_vec_env("Pendulum-v1", n_envs=4, backend="gymnasium", seed=3, env_kwargs=dict(max_episode_steps=30))
    torch_env = make_vec_env("Pendulum-v1", n_envs=4, backend="gymnasium_torch", seed=3, env_kwargs=dict(max_episode_steps=30))
    assert isinstance(torch_env, TorchVecEnv)
    assert_obs_equal(numpy_env.reset(), torch_env.reset())
    cuts = 0
    for step in range(70):
        actions = np.full((4, 1), np.sin(step), np.float32)
        obs, _, dones, infos = numpy_env.step(actions)
        t_obs, _, t_dones, t_infos = torch_env.step(actions)
        assert_obs_equal(obs, t_obs)
        np.testing.assert_array_equal(dones, t_dones)
        for info, t_info in zip(infos, t_infos, strict=True):
            assert info.keys() == t_info.keys()
            if "terminal_observation" in info:
                assert_obs_equal(info["terminal_observation"], t_info["terminal_observation"])
                cuts += "episode" not in info  # a first episode's cut is not reported as an episode
    assert cuts > 0


def test_torch_env_needs_same_step_autoreset():
    venv = gym.make_vec("Pendulum-v1", 2, vectorization_mode="sync")  # NEXT_STEP: gymnasium's default
    with pytest.raises(ValueError, match="same-step autoreset"):
        TorchVecEnv(NumpyToTorchVectorEnv(venv))


def train(kind: str, steps: int = 8 * 120, callback=None, **kwargs):
    env = make_vec_env("Pendulum-v1", n_envs=8, backend=kind, seed=1, env_kwargs=dict(max_episode_steps=40))
    policy_kwargs = dict(net_arch=[32, 32], normalize_observations=True)
    model = CGAC("MlpPolicy", env, batch_size=64, buffer_window=8, policy_kwargs=policy_kwargs, seed=0, **kwargs)
    return model.learn(steps, callback=callback)


@pytest.mark.parametrize("n_steps", [1, 3])
def test_cgac_torch_path_equals_numpy_path(n_steps):
    # The same transitions, targets, updates and episode statistics to the last bit: the torch path changes where
    # the data lives, not what is computed (episodes end by time limits and random first-episode cuts here)
    numpy_model, torch_model = train("gymnasium", n_steps=n_steps), train("gymnasium_torch", n_steps=n_steps)
    torch_parameters = torch_model.policy.state_dict()
    for name, value in numpy_model.policy.state_dict().items():
        assert th.equal(value, torch_parameters[name]), name
    for name in ("returns", "rewards", "next_values", "weights", "truncated", "actions", "next_actions"):
        assert th.equal(getattr(numpy_model.rollout_buffer, name), getattr(torch_model.rollout_buffer, name)), name
    assert numpy_model.rollout_buffer.truncated.any()
    episodes = [[(e["r"], e["l"]) for e in model.ep_info_buffer] for model in (numpy_model, torch_model)]
    assert episodes[0] == episodes[1]
    assert len(torch_model.ep_info_buffer) > 0


def test_reward_entropy_schedule_on_the_device():
    # Eq. 13 on the torch path: the reward average stays on the device and beta is set once per rollout, before the
    # updates read it: the schedule of the NumPy path (up to the float32 mean of the NumPy rewards; Pendulum's: -16 to 0)
    schedules = [RewardEntropySchedule(init_expected_reward=-8.0, peak_expected_reward=-2.0) for _ in range(2)]
    numpy_model = train("gymnasium", steps=8 * 60, n_steps=3, callback=schedules[0])
    torch_model = train("gymnasium_torch", steps=8 * 60, n_steps=3, callback=schedules[1])
    assert schedules[1]._device_average is not None and schedules[0]._device_average is None
    assert schedules[1].reward_average == pytest.approx(schedules[0].reward_average, rel=1e-6)
    assert -8.0 < schedules[0].reward_average < -2.0  # beta strictly between its ends: the schedule moved it
    assert torch_model.target_entropy_beta == pytest.approx(numpy_model.target_entropy_beta, rel=1e-6)


class CopyUnderWay:
    """Stands for the CUDA event of a copy of finished episodes to the host that has not completed."""

    def __init__(self):
        self.complete, self.waited = False, False

    def query(self):
        return self.complete

    def synchronize(self):
        self.waited = self.complete = True


def copies_under_way(monkeypatch):
    copies = []

    def copy_to_host(table):
        copies.append(CopyUnderWay())
        return table.cpu(), copies[-1]

    monkeypatch.setattr(torch_vec_env, "_copy_to_host", copy_to_host)
    return copies


def test_finished_episodes_read_without_waiting(monkeypatch):
    # On a GPU the collection does not wait for the finished episodes: their copy to the host completes in the
    # background and a later call returns them, in order
    copies = copies_under_way(monkeypatch)
    env = reach_envs("torch", n_envs=6)
    env.reset()

    def steps(n):
        for _ in range(n):
            env.step_tensors(th.zeros(6, 2))  # the reach envs' episodes end at their time limit of 25 steps

    steps(30)
    assert env.pop_episodes(wait=False) == [] and len(copies) == 1  # under way
    steps(30)
    copies[0].complete = True
    first = env.pop_episodes(wait=False)
    assert [episode["l"] for episode in first] == [25] * 6 and len(copies) == 2 and not copies[1].waited
    second = env.pop_episodes()  # waits for the copy under way
    assert copies[1].waited and [episode["l"] for episode in second] == [25] * 6
    assert env.pop_episodes() == [] and env.pop_episodes(wait=False) == []


def test_collection_does_not_wait_for_episodes_and_learn_returns_with_every_one(monkeypatch):
    copies = copies_under_way(monkeypatch)  # none completes until learn() waits for it at its end

    class WaitedDuringTraining(BaseCallback):
        waited = False

        def _on_step(self):
            return True

        def _on_rollout_end(self):
            self.waited |= any(copy.waited for copy in copies)

    callback = WaitedDuringTraining()
    numpy_model, torch_model = train("gymnasium"), train("gymnasium_torch", callback=callback)
    assert copies and not callback.waited and all(copy.waited for copy in copies)
    episodes = [[(e["r"], e["l"]) for e in model.ep_info_buffer] for model in (numpy_model, torch_model)]
    assert episodes[0] == episodes[1] and len(episodes[1]) > 0


@pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA device")
def test_finished_episodes_copied_from_the_gpu_in_the_background():
    table = th.arange(24, dtype=th.float64, device="cuda").reshape(2, 3, 4)
    host, done = torch_vec_env._copy_to_host(table)
    assert done is not None and host.is_pinned()
    done.synchronize()
    assert th.equal(host, table.cpu())


def test_collection_takes_no_numpy_step(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("CGAC stepped a TorchVecEnv through SB3's NumPy API")

    monkeypatch.setattr(TorchVecEnv, "step_async", refuse)
    model = train("gymnasium_torch", steps=8 * 20)
    assert model.num_timesteps == 8 * 20


def test_save_load_and_predict(tmp_path):
    model = train("gymnasium_torch", steps=8 * 30)
    model.save(tmp_path / "model")
    env = make_vec_env("Pendulum-v1", n_envs=8, backend="gymnasium_torch", seed=5)
    loaded = CGAC.load(tmp_path / "model", env=env)
    obs = env.reset()
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])
    loaded.learn(8 * 10, reset_num_timesteps=False)  # training goes on from a fresh reset of the new env


def test_dict_observations_and_terminations():
    # An asymmetric policy on a Dict env with terminations and time limits, through both paths
    models = []
    for kind in ("numpy", "torch"):
        policy_kwargs = dict(net_arch=[16, 16], actor_keys=["state"], critic_keys=["state", "privileged_state"])
        env = reach_envs(kind, dict_obs=True)
        model = CGAC("MultiInputPolicy", env, batch_size=48, buffer_window=8, policy_kwargs=policy_kwargs, seed=0)
        models.append(model.learn(6 * 60))
    for a, b in zip(models[0].policy.state_dict().values(), models[1].policy.state_dict().values(), strict=True):
        assert th.equal(a, b)
    assert models[1].rollout_buffer.terminated.any()
