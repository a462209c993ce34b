"""An SB3 ``VecEnv`` over a ``gymnasium.vector.VectorEnv`` (sync, async, or any batched simulator with that API)."""

import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvObs, VecEnvStepReturn

from sb3_cgac.common.obs_rows import per_env_numbers, rows, set_rows

BatchObs = np.ndarray | dict[str, np.ndarray]

EPISODE_AGGREGATIONS = ("sum", "mean", "max", "last")
# Counters that MuJoCo Playground's tasks keep in their infos: successes so far (LeapCube), box out of bounds (Panda)
AUTO_EPISODE_INFO = {"success_count": "last", "out_of_bounds": "max"}


def auto_episode_info(infos: Mapping[str, Any], num_envs: int) -> dict[str, str]:
    """
    The episode statistics that ``episode_info="auto"`` keeps: the sum over the episode of every per-env info
    ``reward_*`` (reward components, as MuJoCo Playground, envpool and gymnasium's MuJoCo envs report them) and the
    Playground counters of ``AUTO_EPISODE_INFO``.
    """
    chosen = {}
    for key, value in infos.items():
        how = "sum" if key.startswith("reward_") else AUTO_EPISODE_INFO.get(key)
        if how is not None and per_env_numbers(value, num_envs):
            chosen[key] = how
    return chosen


def _batch_len(obs: BatchObs) -> int:
    return len(next(iter(obs.values()))) if isinstance(obs, dict) else len(obs)


class GymnasiumVecEnv(VecEnv):
    """
    View a ``gymnasium.vector.VectorEnv`` as a Stable-Baselines3 ``VecEnv``, honouring SB3's episode contract:
    finished envs are reset in the same step, ``infos[i]["terminal_observation"]`` holds the last observation,
    ``infos[i]["TimeLimit.truncated"]`` tells time limits from terminations, and ``infos[i]["episode"]``
    carries the Monitor statistics (return, length, time), so no per-env ``Monitor`` is needed.

    Gymnasium's three autoreset modes are supported: SAME_STEP maps directly; with NEXT_STEP (gymnasium's
    default, and envpool's) and DISABLED, the finished envs are reset at once with ``reset(options={"reset_mask": ...})``,
    so that no step is spent on a reset.

    :param venv: The gymnasium vector env, e.g. from ``gym.make_vec(env_id, num_envs, vector_kwargs=...)``
    :param info_keys: Per-env info entries to copy into SB3's info dicts at every step (each costs a loop over
        envs). ``is_success`` is always copied for finished episodes.
    :param random_first_episode: Cut the first episode of every env after a random number of steps, drawn uniformly
        from ``1..max_episode_steps``, as a time-limit truncation, so that the envs do not all reset at the same
        steps (see ``sb3_cgac.vec_env.wrappers.RandomFirstEpisodeLength``, the same for single envs)
    :param episode_info: Per-env info entries summarised over each episode into ``infos[i]["episode"]`` beside
        ``r`` and ``l``, as ``{key: "sum" | "mean" | "max" | "last"}`` (reward components, task metrics); CGAC logs
        their means as ``rollout/ep_<key>_mean``. ``"auto"``: see ``auto_episode_info``, decided at the first step
        (None: none)
    """

    def __init__(
        self,
        venv: gym.vector.VectorEnv,
        info_keys: Sequence[str] = (),
        random_first_episode: bool = False,
        episode_info: Mapping[str, str] | str | None = "auto",
    ):
        if not isinstance(venv, gym.vector.VectorEnv):
            raise TypeError(
                f"GymnasiumVecEnv wraps a gymnasium.vector.VectorEnv, got {type(venv).__name__}. Build one with "
                "gymnasium.make_vec(env_id, num_envs=...), or use SB3's DummyVecEnv for a list of single envs."
            )
        self.venv = venv
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)
        self.info_keys = tuple(info_keys)
        self.episode_info = self._checked_episode_info(episode_info)
        self._episode_values: dict[str, np.ndarray] = {}
        mode = venv.metadata.get("autoreset_mode", AutoresetMode.NEXT_STEP)
        self.autoreset_mode = AutoresetMode(mode.value if isinstance(mode, AutoresetMode) else mode)
        self._actions: np.ndarray | None = None
        self._episode_returns = np.zeros(self.num_envs, dtype=np.float64)
        self._episode_lengths = np.zeros(self.num_envs, dtype=np.int64)
        self._start_time = time.time()
        self.random_first_episode = random_first_episode
        # Length at which each env's first episode is cut (0: no cut, or the first episode is over)
        self._first_cut = np.zeros(self.num_envs, dtype=np.int64)
        if random_first_episode:
            self.max_episode_steps()  # fail now, not at the first reset

    @staticmethod
    def _checked_episode_info(episode_info: Mapping[str, str] | str | None) -> dict[str, str] | None:
        """The per-key aggregations (None: decided at the first step, for "auto")."""
        if episode_info == "auto":
            return None
        if isinstance(episode_info, str):
            raise ValueError(f'episode_info takes {{info key: aggregation}}, "auto" or None, got {episode_info!r}.')
        chosen = dict(episode_info or {})
        wrong = {key: how for key, how in chosen.items() if how not in EPISODE_AGGREGATIONS}
        if wrong:
            raise ValueError(f"episode_info: unknown aggregation(s) {wrong}; choose from {EPISODE_AGGREGATIONS}.")
        return chosen

    def max_episode_steps(self) -> int:
        """Time limit of the envs' episodes, the range of the random first-episode cuts."""
        spec = getattr(self.venv, "spec", None)
        # gymnasium.make_vec keeps an override of the registered limit in the spec's kwargs, envpool in its config
        limit = getattr(spec, "kwargs", {}).get("max_episode_steps") or getattr(spec, "max_episode_steps", None)
        limit = limit or getattr(getattr(spec, "config", None), "max_episode_steps", None)
        if not limit:
            raise ValueError(
                f"GymnasiumVecEnv: random_first_episode needs the episodes' time limit, and {type(self.venv).__name__} "
                "has none in its spec. Build the vector env from a registered id with a time limit."
            )
        return int(limit)

    def _reset_backend(self, seed: list[int] | None, options: dict[str, Any] | None) -> tuple[BatchObs, dict[str, Any]]:
        # Sync and async vector envs take one seed per env (the base class is typed with a single int)
        return self.venv.reset(seed=seed, options=options)  # type: ignore[arg-type]

    def reset(self) -> VecEnvObs:
        seeds = None if all(seed is None for seed in self._seeds) else [int(seed or 0) for seed in self._seeds]
        options = next((option for option in self._options if option), None)
        obs, infos = self._reset_backend(seeds, options)
        self._reset_seeds()
        self._reset_options()
        self.reset_infos = self._info_dicts(infos)
        self._episode_returns[:] = 0
        self._episode_lengths[:] = 0
        self._episode_values = {}
        if self.random_first_episode:
            rng = np.random.default_rng(self._cut_seed(seeds))
            self._first_cut = rng.integers(1, self.max_episode_steps() + 1, size=self.num_envs)
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> VecEnvStepReturn:
        obs, rewards, terminated, truncated, infos = self.venv.step(self._actions)
        rewards = np.asarray(rewards, dtype=np.float32)
        terminated, truncated = np.asarray(terminated, dtype=bool), np.asarray(truncated, dtype=bool)
        dones = terminated | truncated
        self._episode_returns += rewards
        self._episode_lengths += 1
        step_infos = self._info_dicts(infos)
        same_step = self.autoreset_mode == AutoresetMode.SAME_STEP
        # With SAME_STEP the infos of finished envs are those of their reset, the last step's are in final_info
        final_infos = infos.get("final_info", {}) if same_step else infos
        self._track_episode_info(infos, final_infos, terminated | truncated)
        cut = self._cut_first_episodes(dones)
        if cut is not None:  # a time-limit truncation of envs the vector env did not end itself
            truncated, dones = truncated | cut, dones | cut
        done_idx = np.flatnonzero(dones)
        if len(done_idx) > 0:
            if same_step:
                terminal_obs = infos.get("final_obs")
                terminal_rows = [
                    rows(obs, idx) if cut is not None and cut[idx] else terminal_obs[idx]  # type: ignore[index]
                    for idx in done_idx
                ]
                if cut is not None:
                    obs = self._reset_finished(obs, cut)
            else:
                terminal_rows = self._split_rows(rows(obs, done_idx), len(done_idx))
                obs = self._reset_finished(obs, dones)
            elapsed = round(time.time() - self._start_time, 6)
            for row, idx in enumerate(done_idx):
                info = step_infos[idx]
                info["terminal_observation"] = terminal_rows[row]
                info["TimeLimit.truncated"] = bool(truncated[idx] and not terminated[idx])
                if cut is None or not cut[idx]:  # like Monitor, which never sees the cut of a first episode
                    episode = {"r": float(self._episode_returns[idx]), "l": int(self._episode_lengths[idx]), "t": elapsed}
                    info["episode"] = {**episode, **self._episode_statistics(idx)}
                if "is_success" in final_infos and final_infos.get("_is_success", np.ones(self.num_envs, bool))[idx]:
                    info["is_success"] = final_infos["is_success"][idx]
            self._episode_returns[done_idx] = 0
            self._episode_lengths[done_idx] = 0
            for key, values in self._episode_values.items():
                values[done_idx] = -np.inf if self.episode_info and self.episode_info[key] == "max" else 0.0
        return obs, rewards, dones, step_infos

    def _track_episode_info(self, infos: dict[str, Any], final_infos: dict[str, Any], finished: np.ndarray) -> None:
        """Add this step's info entries to the running episode statistics of ``episode_info``."""
        if self.episode_info is None:  # "auto": decided by the first step's infos
            self.episode_info = auto_episode_info(infos, self.num_envs)
        for key, how in self.episode_info.items():
            if key not in infos:
                continue  # not reported at this step
            if not per_env_numbers(infos[key], self.num_envs):
                raise ValueError(
                    f"episode_info: the info {key!r} holds {np.asarray(infos[key]).shape} values, not one number per env "
                    f"({self.num_envs},); leave it out of episode_info."
                )
            values = np.asarray(infos[key], dtype=np.float64)
            if finished.any() and key in final_infos and final_infos is not infos:
                values = np.where(finished, np.asarray(final_infos[key], dtype=np.float64), values)
            if key not in self._episode_values:
                self._episode_values[key] = np.full(self.num_envs, -np.inf if how == "max" else 0.0)
            current = self._episode_values[key]
            if how in ("sum", "mean"):
                current += values
            elif how == "max":
                np.maximum(current, values, out=current)
            else:
                current[:] = values

    def _episode_statistics(self, idx: int | np.integer) -> dict[str, float]:
        """The ``episode_info`` statistics of the episode that env ``idx`` ends now."""
        assert self.episode_info is not None
        statistics = {}
        for key, values in self._episode_values.items():
            how = self.episode_info[key]
            statistics[key] = float(values[idx] / self._episode_lengths[idx] if how == "mean" else values[idx])
        return statistics

    def _cut_seed(self, seeds: list[int] | None) -> int | None:
        # The first-episode cuts are drawn from the envs' seed, so that seeded runs repeat
        return seeds[0] if seeds is not None else None

    def _cut_first_episodes(self, dones: np.ndarray) -> np.ndarray | None:
        """The envs whose first episode reaches its random cut at this step (None: no env)."""
        if not self.random_first_episode:
            return None
        cut = (self._episode_lengths == self._first_cut) & ~dones
        self._first_cut[dones | cut] = 0  # first episodes that end here are over
        return cut if cut.any() else None

    def _split_rows(self, obs: BatchObs, n_rows: int) -> list[Any]:
        if isinstance(obs, dict):
            return [{key: value[row] for key, value in obs.items()} for row in range(n_rows)]
        return list(obs)

    def _reset_finished(self, obs: BatchObs, dones: np.ndarray) -> BatchObs:
        """Reset the finished envs now (NEXT_STEP / DISABLED modes) and put their first observation in the batch."""
        reset_obs, reset_infos = self.venv.reset(options={"reset_mask": dones})
        done_idx = np.flatnonzero(dones)
        if _batch_len(reset_obs) == self.num_envs:  # gymnasium returns every env
            reset_obs = rows(reset_obs, done_idx)
        elif "env_id" in reset_infos:  # envpool returns the reset envs only, with their ids
            order = np.argsort(np.asarray(reset_infos["env_id"]))
            reset_obs = rows(reset_obs, order)
        obs = {key: np.array(value) for key, value in obs.items()} if isinstance(obs, dict) else np.array(obs)
        set_rows(obs, done_idx, reset_obs)
        return obs

    def _info_dicts(self, infos: dict[str, Any]) -> list[dict[str, Any]]:
        # Gymnasium batches infos as {key: array, "_key": mask}; SB3 wants one dict per env
        dicts: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        for key in self.info_keys:
            if key in infos:
                mask = infos.get(f"_{key}", np.ones(self.num_envs, dtype=bool))
                for idx in np.flatnonzero(mask):
                    dicts[idx][key] = infos[key][idx]
        return dicts

    def close(self) -> None:
        self.venv.close()

    def _indices(self, indices: VecEnvIndices) -> list[int]:
        if indices is None:
            return list(range(self.num_envs))
        if isinstance(indices, int):
            return [indices]
        return list(indices)

    def _vector_method(self, name: str) -> Callable[..., Any]:
        # get_attr / set_attr / call belong to gymnasium's sync and async vector envs, not to every VectorEnv
        method = getattr(self.venv, name, None)
        if method is None:
            raise NotImplementedError(f"GymnasiumVecEnv: {type(self.venv).__name__} has no {name}() method.")
        return method

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        if attr_name == "render_mode":
            values: Sequence[Any] = [getattr(self.venv, "render_mode", None)] * self.num_envs
        else:
            values = self._vector_method("get_attr")(attr_name)
        return [values[idx] for idx in self._indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        set_attr = self._vector_method("set_attr")
        if indices is None:
            set_attr(attr_name, [value] * self.num_envs)
            return
        # Gymnasium sets all envs at once: keep the others' current values
        try:
            values = list(self._vector_method("get_attr")(attr_name))
        except AttributeError as error:
            raise AttributeError(
                f"GymnasiumVecEnv: {attr_name!r} does not exist yet; gymnasium vector envs can only create an "
                "attribute on all envs at once (indices=None)."
            ) from error
        for idx in self._indices(indices):
            values[idx] = value
        set_attr(attr_name, values)

    def env_method(
        self, method_name: str, *method_args: Any, indices: VecEnvIndices = None, **method_kwargs: Any
    ) -> list[Any]:
        results = self._vector_method("call")(method_name, *method_args, **method_kwargs)
        return [results[idx] for idx in self._indices(indices)]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        # The episode statistics of this adapter stand in for a Monitor wrapper
        if issubclass(Monitor, wrapper_class):
            return [True for _ in self._indices(indices)]
        envs: Iterable[gym.Env] | None = getattr(self.venv, "envs", None)
        if envs is None:
            return [False for _ in self._indices(indices)]
        env_list = list(envs)
        return [_is_wrapped(env_list[idx], wrapper_class) for idx in self._indices(indices)]


def _is_wrapped(env: gym.Env, wrapper_class: type[gym.Wrapper]) -> bool:
    while isinstance(env, gym.Wrapper):
        if isinstance(env, wrapper_class):
            return True
        env = env.env
    return False
