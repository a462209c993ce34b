"""Gymnasium and SB3 VecEnv wrappers for training with many parallel envs."""

from collections.abc import Sequence
from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper
from stable_baselines3.common.vec_env.base_vec_env import VecEnvObs, VecEnvStepReturn


class RandomFirstEpisodeLength(gym.Wrapper):
    """
    Cut the first episode of the env at a random length, drawn uniformly from ``1..max_episode_steps``, as a
    time-limit truncation (``truncated=True``; SB3's VecEnvs then report ``TimeLimit.truncated`` with the
    terminal observation, so CGAC bootstraps the value target as for any time limit). The episodes that follow
    an episode end (the VecEnv's automatic resets) are left alone; any other reset (``env.reset()`` of the whole
    VecEnv, which puts every env back at the same step) draws a new cut.

    Why: envs built and reset together hit their time limits together, so a few steps after every synchronised
    reset CGAC's window of recent steps holds only initial states (paper Sec. 4.2, "Policy-Value Coupling"). With
    a random first cut the episodes of the parallel envs are spread evenly over the episode length from then on:
    a simpler equivalent of the authors' reset throttling, which needs per-env resets that SB3's VecEnv API
    does not offer. Use it as the ``wrapper_class`` of ``make_vec_env`` (or an rl-zoo ``env_wrapper``).

    :param env: The env to wrap
    :param max_episode_steps: Longest first episode (None: the env's registered time limit)
    """

    def __init__(self, env: gym.Env, max_episode_steps: int | None = None):
        super().__init__(env)
        if max_episode_steps is None:
            max_episode_steps = env.spec.max_episode_steps if env.spec is not None else None
        if max_episode_steps is None or max_episode_steps < 1:
            raise ValueError(
                f"RandomFirstEpisodeLength needs the episode length to draw from: {env} has no registered time limit "
                "(env.spec.max_episode_steps). Pass max_episode_steps."
            )
        self.max_episode_steps = int(max_episode_steps)
        # Steps left before the cut of the current episode; None when it runs to its end
        self._steps_left: int | None = None
        # Whether the last step ended the episode, so that the next reset is an automatic one
        self._episode_ended = False
        # An own generator: drawing from the env's would change the env's later episodes
        self._rng: np.random.Generator | None = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(seed=seed, options=options)
        if self._episode_ended:
            self._steps_left = None
        else:
            if seed is not None or self._rng is None:
                self._rng = np.random.default_rng(seed)
            self._steps_left = int(self._rng.integers(1, self.max_episode_steps + 1))
        self._episode_ended = False
        return obs, info

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        if self._steps_left is not None:
            self._steps_left -= 1
            if self._steps_left == 0 and not (terminated or truncated):
                truncated = True
        self._episode_ended = bool(terminated or truncated)
        return obs, reward, terminated, truncated, info


class VecObservationKeys(VecEnvWrapper):
    """
    Keep some keys of a Dict observation, in the observations and in ``infos[i]["terminal_observation"]``: an
    algorithm without per-key inputs (SB3's PPO, SAC) then reads only what a robot senses, e.g. ``keys=["state"]``
    of the MuJoCo Playground tasks. In rl-zoo YAML: ``vec_env_wrapper: [{sb3_cgac.vec_env.wrappers.VecObservationKeys:
    {keys: [state]}}]``.

    :param venv: The vector env, with a Dict observation space
    :param keys: The keys to keep
    """

    def __init__(self, venv: VecEnv, keys: Sequence[str]):
        space = venv.observation_space
        if not isinstance(space, spaces.Dict):
            raise ValueError(f"VecObservationKeys selects keys of a Dict observation space, got {space}.")
        unknown = sorted(set(keys) - set(space.spaces))
        if unknown or not keys:
            raise ValueError(f"VecObservationKeys: keys {list(keys)} must be some of the observation's {list(space.spaces)}.")
        self.keys = list(keys)
        super().__init__(venv, observation_space=spaces.Dict({key: space[key] for key in self.keys}))

    def _select(self, obs: Any) -> dict[str, np.ndarray]:
        return {key: obs[key] for key in self.keys}

    def reset(self) -> VecEnvObs:
        return self._select(self.venv.reset())

    def step_wait(self) -> VecEnvStepReturn:
        obs, rewards, dones, infos = self.venv.step_wait()
        for info in infos:
            if "terminal_observation" in info:
                info["terminal_observation"] = self._select(info["terminal_observation"])
        return self._select(obs), rewards, dones, infos
