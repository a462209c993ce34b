"""An SB3 ``VecEnv`` over an envpool batch: all envs stepped by one C++ thread pool."""

import os
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env.base_vec_env import VecEnvIndices

from sb3_cgac.threads import thread_spin_configured
from sb3_cgac.vec_env.gymnasium_vec_env import BatchObs, GymnasiumVecEnv


def _import_envpool() -> Any:
    try:
        import envpool
    except ImportError as error:
        raise ImportError("EnvPoolVecEnv needs envpool: pip install 'sb3_cgac[envpool]' (or pip install envpool).") from error
    return envpool


def _warn_if_torch_spins() -> None:
    if not thread_spin_configured():
        warnings.warn(
            "torch's OpenMP threads spin for milliseconds after each op and slow envpool's threads down (on 2 cores, "
            "CGAC's collection dropped from a median 82% to about 60% of envpool's speed). Call "
            "sb3_cgac.threads.configure_thread_spin() before anything imports torch, or start Python with "
            "GOMP_SPINCOUNT=10000.",
            UserWarning,
            stacklevel=3,
        )


class EnvPoolVecEnv(GymnasiumVecEnv):
    """
    Stable-Baselines3 ``VecEnv`` over an envpool batch (extra ``envpool``). envpool steps every env in C++
    threads; this adapter turns its next-step autoreset into SB3's same-step contract (``terminal_observation``,
    ``TimeLimit.truncated``, Monitor-style ``episode`` statistics) with a partial reset of the finished envs.

    envpool's physics is its own build of MuJoCo: episodes match gymnasium's in structure (spaces, time limits,
    termination rules, reward terms) but not bit for bit (see ``tests/test_vec_env.py``).

    :param env_id: envpool task id, e.g. ``"HalfCheetah-v5"`` (``envpool.list_all_envs()`` lists them)
    :param num_envs: Number of parallel envs
    :param seed: Seed of the envs (env i gets ``seed + i``); envpool fixes seeds at creation, so ``seed()``
        rebuilds the pool at the next reset
    :param num_threads: Threads of envpool's pool (None: one per CPU core)
    :param info_keys: Per-env info entries to copy into SB3's info dicts at every step
    :param random_first_episode: Cut the first episode of every env at a random length (see ``GymnasiumVecEnv``)
    :param episode_info: Info entries summarised over each episode into ``infos[i]["episode"]`` (see
        ``GymnasiumVecEnv``; ``"auto"``: the reward components ``reward_*`` summed, and the MuJoCo Playground tasks'
        counters, e.g. LeapCube's ``success_count``)
    :param env_kwargs: Other keyword arguments of ``envpool.make_gymnasium`` (e.g. ``max_episode_steps``)
    """

    def __init__(
        self,
        env_id: str,
        num_envs: int,
        seed: int = 0,
        num_threads: int | None = None,
        info_keys: Sequence[str] = (),
        random_first_episode: bool = False,
        episode_info: Mapping[str, str] | str | None = "auto",
        **env_kwargs: Any,
    ):
        self.env_id = env_id
        self.num_threads = num_threads if num_threads is not None else (os.cpu_count() or 1)
        self.env_kwargs = env_kwargs
        self.current_seed = seed
        _warn_if_torch_spins()
        super().__init__(
            self._make_pool(num_envs, seed),
            info_keys=info_keys,
            random_first_episode=random_first_episode,
            episode_info=episode_info,
        )
        if isinstance(self.action_space, spaces.Box) and self.action_space.dtype == np.float64:
            # Gymnasium's MuJoCo envs declare float32 actions: match them, so that a model trained here
            # loads onto the gymnasium env (SB3 compares the spaces)
            self.action_space = spaces.Box(
                self.action_space.low.astype(np.float32), self.action_space.high.astype(np.float32), dtype=np.float32
            )

    def _make_pool(self, num_envs: int, seed: int) -> gym.vector.VectorEnv:
        envpool = _import_envpool()
        if self.env_id not in envpool.list_all_envs():
            raise ValueError(
                f"envpool has no task {self.env_id!r}; envpool.list_all_envs() lists the available ones "
                "(for other envs use the 'dummy', 'subproc' or 'gymnasium' backends)."
            )
        return envpool.make_gymnasium(
            self.env_id, num_envs=num_envs, seed=seed, num_threads=min(self.num_threads, num_envs), **self.env_kwargs
        )

    def _reset_backend(self, seed: list[int] | None, options: dict[str, Any] | None) -> tuple[BatchObs, dict[str, Any]]:
        if seed is not None and seed[0] != self.current_seed:
            # envpool seeds its envs when it is created (env i gets seed + i): build a new pool
            self.venv.close()
            self.current_seed = seed[0]
            self.venv = self._make_pool(self.num_envs, self.current_seed)
        return self.venv.reset(options=options)

    def _cut_seed(self, seeds: list[int] | None) -> int | None:
        return self.current_seed

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        # The envs live in C++: only the pool's own attributes can be read
        if attr_name == "render_mode":
            return [None for _ in self._indices(indices)]
        if not hasattr(self.venv, attr_name):
            raise AttributeError(f"EnvPoolVecEnv: envpool's pool has no attribute {attr_name!r}.")
        value = getattr(self.venv, attr_name)
        return [value for _ in self._indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        raise NotImplementedError("EnvPoolVecEnv: envpool's envs are C++ objects whose attributes cannot be set.")

    def env_method(
        self, method_name: str, *method_args: Any, indices: VecEnvIndices = None, **method_kwargs: Any
    ) -> list[Any]:
        raise NotImplementedError(
            f"EnvPoolVecEnv: envpool's envs are C++ objects, env_method({method_name!r}) cannot call them. "
            "Use the 'dummy' or 'gymnasium' backends if you need per-env methods."
        )
