"""
Torch-native vectorised envs: batched simulators whose step takes and returns torch tensors on a device (GPU
simulators), so that CGAC collects without a copy to the host at each step.

The contract is gymnasium's vector API with torch tensors: a ``gymnasium.vector.VectorEnv`` whose ``step(actions)``
takes an action tensor and returns ``(obs, rewards, terminated, truncated, info)`` as tensors (a Dict observation as
a dict of tensors), with same-step autoreset (``metadata["autoreset_mode"] = AutoresetMode.SAME_STEP``): a finished
env is reset within the step, ``obs`` holds its first observation and ``info["final_obs"]`` the last one, batched
like ``obs`` (the rows of the envs that did not finish are not read). Info entries ``reward_*`` with one number per
env (reward components; a finished env's from its last step) are summed over each episode into its statistics. It is
the one of the common interfaces that tells time limits from terminations *and* keeps the real last observation,
which CGAC's value targets bootstrap from at a time limit (paper Sec. 4.1); rsl_rl's ``VecEnv`` and Isaac Lab's envs
report time-outs without it. Gymnasium's own ``NumpyToTorch`` wrapper cannot carry same-step autoreset's ``final_obs``
(a NumPy object array); ``NumpyToTorchVectorEnv``
below does, so that any gymnasium vector env can take this path (on a CPU it mainly serves as a reference).

``TorchVecEnv`` makes such an env an SB3 ``VecEnv``: SB3's NumPy API (evaluation, SB3's algorithms, ``VecNormalize``)
keeps working, and ``step_tensors`` is the path without NumPy that CGAC takes when it trains on a ``TorchVecEnv``.
"""

from collections.abc import Sequence
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvObs, VecEnvStepReturn

from sb3_cgac.common.obs_rows import TensorObs, per_env_numbers, where_rows


class TensorStep(NamedTuple):
    """One step of every env of a ``TorchVecEnv``, as tensors on its device."""

    observations: TensorObs  # after the reset of the envs that finished
    rewards: th.Tensor  # float32, (n_envs,)
    terminated: th.Tensor  # bool: the episode ended in a terminal state
    truncated: th.Tensor  # bool: a time limit, or the random cut of a first episode (and not terminated)
    final_observations: TensorObs  # the last observation of the finished envs' episodes (other rows: arbitrary)
    infos: dict[str, Any]


def reward_components(info: dict[str, Any], num_envs: int) -> list[str]:
    """The info entries that a torch-native env's episode statistics sum: ``reward_*``, one number per env."""
    return [key for key, value in info.items() if key.startswith("reward_") and per_env_numbers(value, num_envs)]


def _to_numpy(obs: TensorObs) -> np.ndarray | dict[str, np.ndarray]:
    if isinstance(obs, dict):
        return {key: value.cpu().numpy() for key, value in obs.items()}
    return obs.cpu().numpy()


def _episode(row: np.ndarray, component_keys: list[str]) -> dict[str, float]:
    # A row of a table of finished episodes: (finished, return, length, component sums...)
    sums = dict(zip(component_keys, map(float, row[3:]), strict=True))
    return {"r": float(row[1]), "l": int(row[2]), **sums}


def _copy_to_host(table: th.Tensor) -> tuple[th.Tensor, th.cuda.Event | None]:
    """
    ``table`` copied to the host: from a GPU into pinned memory without waiting, with the event that marks the end of
    the copy; else at once (None).
    """
    if table.device.type != "cuda":
        return table.cpu(), None
    try:
        host = th.empty(table.shape, dtype=table.dtype, pin_memory=True)
    except RuntimeError:  # no page-locked memory here: a copy that waits
        return table.cpu(), None
    host.copy_(table, non_blocking=True)
    done = th.cuda.Event()
    done.record()
    return host, done


def _to_tensor(value: Any, device: th.device, dtype: th.dtype | None = None) -> Any:
    if isinstance(value, dict):
        return {key: _to_tensor(item, device, dtype) for key, item in value.items()}
    return th.as_tensor(value, device=device, dtype=dtype)


class TorchVecEnv(VecEnv):
    """
    An SB3 ``VecEnv`` over a torch-native ``gymnasium.vector.VectorEnv`` (see the module's docstring for the
    contract). Episode returns and lengths are kept on the device; ``step_tensors`` returns the step as tensors and
    ``pop_episodes`` the finished episodes (one host read, or none to wait for), while SB3's ``step`` gives NumPy
    arrays and one info dict per env (``terminal_observation``, ``TimeLimit.truncated``, ``episode``), as the
    other adapters do.

    :param venv: The torch-native vector env
    :param device: Device of its tensors (None: ``venv.device`` when it has one, else the CPU)
    :param random_first_episode: Cut the first episode of every env after a random number of steps, drawn uniformly
        from ``1..max_episode_steps`` with the envs' seed, as a time-limit truncation, so that the envs do not all
        reset at the same steps (as ``GymnasiumVecEnv`` does; the venv's ``reset`` must take
        ``options={"reset_mask": mask}``). The cuts fall at steps known in advance: no host sync
    :param max_episode_steps: Time limit of the episodes, the range of the random cuts (None: the venv's spec)
    """

    def __init__(
        self,
        venv: gym.vector.VectorEnv,
        device: th.device | str | None = None,
        random_first_episode: bool = False,
        max_episode_steps: int | None = None,
    ):
        mode = venv.metadata.get("autoreset_mode")
        if AutoresetMode(getattr(mode, "value", mode) or AutoresetMode.NEXT_STEP.value) != AutoresetMode.SAME_STEP:
            raise ValueError(
                f"TorchVecEnv needs a vector env with same-step autoreset (metadata['autoreset_mode'] = "
                f"AutoresetMode.SAME_STEP, final observations in info['final_obs']); {type(venv).__name__} has {mode}. "
                "Build it with gymnasium.make_vec(..., vector_kwargs={'autoreset_mode': AutoresetMode.SAME_STEP})."
            )
        self.venv = venv
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)
        self.device = th.device(device if device is not None else getattr(venv, "device", None) or "cpu")
        self.random_first_episode = random_first_episode
        self._max_episode_steps = max_episode_steps
        if random_first_episode:
            self.max_episode_steps()  # fail now, not at the first reset
        assert isinstance(self.action_space, gym.spaces.Box), "TorchVecEnv: continuous (Box) actions only"
        self._last_obs: TensorObs | None = None
        self._actions: np.ndarray | None = None
        self._returns = th.zeros(self.num_envs, dtype=th.float64, device=self.device)
        self._lengths = th.zeros(self.num_envs, dtype=th.int64, device=self.device)
        self._first_cut = th.zeros(self.num_envs, dtype=th.int64, device=self.device)
        self._cut_steps: set[int] = set()  # steps since the reset at which some first episode may be cut
        self._steps_since_reset = 0
        # Reward components (chosen at the first step: ``reward_components``), summed over the running episodes
        self._component_keys: list[str] | None = None
        self._component_sums = th.zeros((0, self.num_envs), dtype=th.float64, device=self.device)
        # Per step: finished (as Monitor reports), returns, lengths and component sums, one (3 + components, envs) tensor
        self._finished: list[th.Tensor] = []
        # Tables of finished episodes on their way to the host: the host tensor, the event that marks the end of its
        # copy (None: complete), the component keys they were summed under
        self._copies: list[tuple[th.Tensor, th.cuda.Event | None, list[str]]] = []

    @property
    def last_observations(self) -> TensorObs:
        """The observations of the envs now (after ``reset`` or the latest step), as tensors."""
        if self._last_obs is None:
            raise RuntimeError("TorchVecEnv: reset() the env before stepping it.")
        return self._last_obs

    def max_episode_steps(self) -> int:
        """Time limit of the episodes, the range of the random first-episode cuts."""
        spec = getattr(self.venv, "spec", None)
        limit = self._max_episode_steps or getattr(self.venv, "max_episode_steps", None)
        limit = limit or getattr(spec, "kwargs", {}).get("max_episode_steps")
        limit = limit or getattr(spec, "max_episode_steps", None)
        if not limit:
            raise ValueError(
                f"TorchVecEnv: random_first_episode needs the episodes' time limit; {type(self.venv).__name__} has none in "
                "its spec. Pass max_episode_steps."
            )
        return int(limit)

    def reset_tensors(self) -> TensorObs:
        """Reset every env (with the seed given to ``seed()``, if any); the observations as tensors."""
        seed = self._seeds[0]
        obs, _ = self.venv.reset(seed=None if seed is None else int(seed), options=self._options[0] or None)
        self._reset_seeds()
        self._reset_options()
        self._last_obs = _to_tensor(obs, self.device)
        self._returns.zero_()
        self._lengths.zero_()
        self._component_keys = None
        self._finished = []
        self._steps_since_reset = 0
        if self.random_first_episode:
            cuts = np.random.default_rng(seed).integers(1, self.max_episode_steps() + 1, size=self.num_envs)
            self._first_cut = th.as_tensor(cuts, device=self.device)
            self._cut_steps = {int(cut) for cut in cuts}
        return self._last_obs

    def step_tensors(self, actions: th.Tensor) -> TensorStep:
        """Step every env with ``actions`` (unscaled, on any device); the step as tensors on this env's device."""
        obs, rewards, terminated, truncated, info = self.venv.step(actions.to(self.device))
        obs = _to_tensor(obs, self.device)
        rewards = _to_tensor(rewards, self.device, th.float32)
        terminated = _to_tensor(terminated, self.device, th.bool)
        truncated = _to_tensor(truncated, self.device, th.bool) & ~terminated
        final = _to_tensor(info["final_obs"], self.device) if "final_obs" in info else obs
        dones = terminated | truncated
        self._steps_since_reset += 1
        self._returns += rewards
        self._lengths += 1
        if self._component_keys is None:
            self._component_keys = reward_components(info, self.num_envs)
            self._component_sums = self._returns.new_zeros((len(self._component_keys), self.num_envs))
        if self._component_keys:
            self._component_sums += th.stack([self._info_numbers(info, key) for key in self._component_keys])
        reported = dones
        if self.random_first_episode:
            self._first_cut.masked_fill_(dones, 0)  # first episodes that end on their own are over
            if self._steps_since_reset in self._cut_steps:  # cuts fall at steps known at the reset: no host sync
                cut = self._lengths == self._first_cut
                self._first_cut.masked_fill_(cut, 0)
                reset_obs, _ = self.venv.reset(options={"reset_mask": cut})
                final = where_rows(cut, obs, final)
                obs = where_rows(cut, _to_tensor(reset_obs, self.device), obs)
                truncated, dones = truncated | cut, dones | cut
        # Like Monitor, which never sees the cut of a first episode
        episode = th.stack([reported.double(), self._returns, self._lengths.double()])
        self._finished.append(th.cat([episode, self._component_sums]))
        self._returns.masked_fill_(dones, 0)
        self._lengths.masked_fill_(dones, 0)
        self._component_sums.masked_fill_(dones, 0)
        self._last_obs = obs
        return TensorStep(obs, rewards, terminated, truncated, final, info)

    def pop_episodes(self, wait: bool = True) -> list[dict[str, float]]:
        """
        The finished episodes not returned yet, in the order they finished, as Monitor reports them (``r``, ``l``),
        with their reward components' sums: one host read.

        :param wait: False: do not wait for the device. On a GPU the episodes finished since the last call are copied
            to the host in the background and a later call returns them (each call returns those whose copy has
            completed); on a CPU it makes no difference
        """
        if self._finished:
            table, done = _copy_to_host(th.stack(self._finished))  # (steps, 3 + components, envs)
            self._copies.append((table, done, list(self._component_keys or [])))
            self._finished = []
        episodes = []
        while self._copies and (wait or self._copies[0][1] is None or self._copies[0][1].query()):
            table, done, keys = self._copies.pop(0)
            if done is not None:
                done.synchronize()
            array = table.numpy()
            rows = np.moveaxis(array, 1, -1)[array[:, 0] > 0]  # one row per finished episode, in step and env order
            episodes += [_episode(row, keys) for row in rows]
        return episodes

    def _info_numbers(self, info: dict[str, Any], key: str) -> th.Tensor:
        if key not in info:  # not reported at this step
            return self._returns.new_zeros(self.num_envs)
        return _to_tensor(info[key], self.device, th.float64)

    # SB3's NumPy API

    def reset(self) -> VecEnvObs:
        return _to_numpy(self.reset_tensors())

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> VecEnvStepReturn:
        assert self._actions is not None
        step = self.step_tensors(th.as_tensor(self._actions, dtype=th.float32))
        table = self._finished.pop().cpu().numpy().T  # (envs, 3 + components)
        dones = (step.terminated | step.truncated).cpu().numpy()
        truncated = step.truncated.cpu().numpy()
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        final = _to_numpy(step.final_observations)
        for idx in np.flatnonzero(dones):
            infos[idx]["terminal_observation"] = (
                {key: value[idx] for key, value in final.items()} if isinstance(final, dict) else final[idx]
            )
            infos[idx]["TimeLimit.truncated"] = bool(truncated[idx])
        for idx in np.flatnonzero(table[:, 0] > 0):  # the envs whose episode Monitor would report
            infos[idx]["episode"] = _episode(table[idx], self._component_keys or [])
        return _to_numpy(step.observations), step.rewards.cpu().numpy(), dones, infos

    def close(self) -> None:
        self.venv.close()

    def _indices(self, indices: VecEnvIndices) -> list[int]:
        if indices is None:
            return list(range(self.num_envs))
        return [indices] if isinstance(indices, int) else list(indices)

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        value = getattr(self.venv, attr_name, None) if attr_name == "render_mode" else getattr(self.venv, attr_name)
        return [value for _ in self._indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        setattr(self.venv, attr_name, value)

    def env_method(
        self, method_name: str, *method_args: Any, indices: VecEnvIndices = None, **method_kwargs: Any
    ) -> list[Any]:
        result = getattr(self.venv, method_name)(*method_args, **method_kwargs)
        return [result for _ in self._indices(indices)]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        # The episode statistics of this adapter stand in for a Monitor wrapper
        return [issubclass(Monitor, wrapper_class) for _ in self._indices(indices)]


class NumpyToTorchVectorEnv(gym.vector.VectorWrapper):
    """
    A NumPy ``gymnasium.vector.VectorEnv`` with same-step autoreset (e.g. ``gymnasium.make_vec(env_id, n,
    vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP})``) seen through the torch-native contract: tensors
    on ``device``, and ``info["final_obs"]`` batched like the observations. The reference torch-native env of the
    tests, and a way to run any gymnasium env on the torch path.

    :param env: The NumPy vector env
    :param device: Device of the returned tensors
    """

    def __init__(self, env: gym.vector.VectorEnv, device: th.device | str = "cpu"):
        super().__init__(env)
        self.device = th.device(device)
        self._obs: Any = None

    def reset(self, *, seed: int | Sequence[int] | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict]:
        if options and "reset_mask" in options:
            mask = np.asarray(th.as_tensor(options["reset_mask"]).cpu())
            if not mask.any():  # gymnasium refuses an empty mask: nothing to reset
                return self._obs, {}
            options = {**options, "reset_mask": mask}
        obs, info = self.env.reset(seed=seed, options=options)  # type: ignore[arg-type]
        self._obs = _to_tensor(obs, self.device)
        return self._obs, info

    def step(self, actions: Any) -> tuple[Any, Any, Any, Any, dict[str, Any]]:
        actions = th.as_tensor(actions).cpu().numpy()
        obs, rewards, terminated, truncated, info = self.env.step(actions)
        final = info.get("final_obs")
        if final is not None:  # an object array, None where the env did not finish: batch it like obs
            mask = info["_final_obs"]
            if isinstance(obs, dict):
                batched = {key: np.array(value) for key, value in obs.items()}
                for idx in np.flatnonzero(mask):
                    for key in batched:
                        batched[key][idx] = final[idx][key]
                info = {**info, "final_obs": _to_tensor(batched, self.device)}
            else:
                rows = np.array(obs)
                rows[mask] = np.stack([final[idx] for idx in np.flatnonzero(mask)])
                info = {**info, "final_obs": _to_tensor(rows, self.device)}
        info = {**info, **self._reward_components(info, np.asarray(terminated) | np.asarray(truncated))}
        self._obs = _to_tensor(obs, self.device)
        return (
            self._obs,
            _to_tensor(rewards, self.device),
            _to_tensor(terminated, self.device),
            _to_tensor(truncated, self.device),
            info,
        )

    def _reward_components(self, info: dict[str, Any], finished: np.ndarray) -> dict[str, th.Tensor]:
        # Same-step autoreset gives a finished env its reset's infos: its last step's components are in final_info
        final_info = info.get("final_info", {})
        keys = dict.fromkeys([*reward_components(info, self.num_envs), *reward_components(final_info, self.num_envs)])
        components = {}
        for key in keys:
            values = np.asarray(info.get(key, np.zeros(self.num_envs)), dtype=np.float64)
            if key in final_info:
                values = np.where(finished, np.asarray(final_info[key], dtype=np.float64), values)
            components[key] = _to_tensor(values, self.device)
        return components
