"""
From an env step to the window's input, one format for every env: tensors on the policy's device, observations
sanitised, SB3's ``dones`` split into terminations and time-limit truncations, and the real last observations that a
truncated step's value target bootstraps from (paper Sec. 4.1). An SB3 VecEnv's NumPy step is converted here, once
(``vec_env_step``); a torch-native env (``sb3_cgac.vec_env.TorchVecEnv``) gives tensors already (``tensor_env_step``).
"""

from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import torch as th
from stable_baselines3.common.utils import obs_as_tensor

from sb3_cgac.common.obs_rows import ArrayObs, TensorObs, set_rows, where_rows

if TYPE_CHECKING:
    from sb3_cgac.vec_env.torch_vec_env import TensorStep

# Observations with a larger magnitude are treated as corrupt, as in the paper's code
OBS_ABS_LIMIT = 1e6


class EnvStep(NamedTuple):
    """One step of every env as the window stores it: tensors on the policy's device, whichever env gave it."""

    observations: TensorObs  # sanitised, after the reset of the envs that finished
    obs_ok: th.Tensor  # bool: which rows were usable before sanitising
    rewards: th.Tensor  # float32, as the env gave them (the window excludes the non-finite ones)
    terminated: th.Tensor  # bool: the episode ended in a terminal state
    truncated: th.Tensor  # bool: a time limit cut the episode, its value target bootstraps
    # The real last observations of the truncated envs' episodes, sanitised, and their validity (the other rows are
    # arbitrary); None where the env tells on the host that no episode was truncated (an SB3 VecEnv, most steps)
    final_observations: TensorObs | None
    final_ok: th.Tensor | None
    infos: list[dict[str, Any]] | dict[str, Any]

    @property
    def dones(self) -> th.Tensor:
        return self.terminated | self.truncated

    def bootstrap_observations(self) -> TensorObs:
        """The observations the next actions of this step are drawn at (paper Sec. 4.1)."""
        if self.final_observations is None:
            return self.observations
        return where_rows(self.truncated, self.final_observations, self.observations)


def vec_env_step(
    new_obs: Any, rewards: np.ndarray, dones: np.ndarray, infos: list[dict[str, Any]], device: th.device
) -> EnvStep:
    """One step of an SB3 VecEnv (``VecEnv.step``'s return values, SB3's episode contract) as the window stores it."""
    terminated, truncated = split_episode_ends(dones, infos)
    obs, ok = sanitize_observations(new_obs)
    final_obs: TensorObs | None = None
    final_ok: th.Tensor | None = None
    if truncated.any():
        final_array, final_array_ok = final_observations(obs, ok, infos, np.flatnonzero(truncated))
        final_obs, final_ok = obs_as_tensor(final_array, device), th.as_tensor(final_array_ok, device=device)
    return EnvStep(
        obs_as_tensor(obs, device),
        th.as_tensor(ok, device=device),
        th.as_tensor(np.asarray(rewards, dtype=np.float32), device=device),
        th.as_tensor(terminated, device=device),
        th.as_tensor(truncated, device=device),
        final_obs,
        final_ok,
        infos,
    )


def vec_env_observations(obs: ArrayObs, device: th.device) -> tuple[TensorObs, th.Tensor]:
    """Observations of an SB3 VecEnv (a reset's) on ``device``, sanitised (see ``sanitize_observations``)."""
    obs, ok = sanitize_observations(obs)
    return obs_as_tensor(obs, device), th.as_tensor(ok, device=device)


def tensor_env_step(step: "TensorStep", device: th.device) -> EnvStep:
    """One step of a torch-native env (``TorchVecEnv.step_tensors``) as the window stores it, on ``device``."""
    obs, obs_ok = tensor_observations(step.observations, device)
    final_obs, final_ok = tensor_observations(step.final_observations, device)
    rewards, terminated, truncated = step.rewards.to(device, th.float32), step.terminated.to(device), step.truncated.to(device)
    return EnvStep(obs, obs_ok, rewards, terminated, truncated, final_obs, final_ok, step.infos)


def tensor_observations(obs: TensorObs, device: th.device) -> tuple[TensorObs, th.Tensor]:
    """Observations of a torch-native env on ``device``, sanitised (see ``sanitize_tensor_observations``)."""
    if isinstance(obs, dict):
        return sanitize_tensor_observations({key: value.to(device) for key, value in obs.items()})
    return sanitize_tensor_observations(obs.to(device))


def sanitize_observations(obs: ArrayObs) -> tuple[ArrayObs, np.ndarray]:
    """
    Find the envs whose observation holds NaN, Inf or values beyond ``OBS_ABS_LIMIT`` and zero them,
    so that no network ever sees them; the returned mask lets the window exclude those transitions.

    NumPy at the boundary, before the conversion to tensors: a batch of an SB3 VecEnv is checked by one reduction in the
    common case (docs/performance.md, "One tensor pipeline").

    :param obs: Batched observations (one row per env), an array or a dict of arrays
    :return: The cleaned observations (float ones in float32, the precision of the networks and the window)
        and a boolean array, True where the row is usable
    """
    if isinstance(obs, dict):
        cleaned = {key: _sanitize_array(value) for key, value in obs.items()}
        ok = np.logical_and.reduce([key_ok for _, key_ok in cleaned.values()])
        return {key: value for key, (value, _) in cleaned.items()}, ok
    return _sanitize_array(obs)


def sanitize_tensor_observations(obs: TensorObs) -> tuple[TensorObs, th.Tensor]:
    """
    ``sanitize_observations`` for observations that are already tensors (torch-native envs), on their device and
    without a host sync: the rows that hold NaN, Inf or values beyond ``OBS_ABS_LIMIT`` are zeroed.

    :return: The cleaned observations (float ones in float32) and a boolean tensor, True where the row is usable
    """
    if isinstance(obs, dict):
        cleaned = {key: _sanitize_tensor(value) for key, value in obs.items()}
        ok = th.stack([key_ok for _, key_ok in cleaned.values()]).all(dim=0)
        return {key: value for key, (value, _) in cleaned.items()}, ok
    return _sanitize_tensor(obs)


def split_episode_ends(dones: np.ndarray, infos: list[dict[str, Any]]) -> tuple[np.ndarray, np.ndarray]:
    """
    Split SB3's ``dones`` into terminations and time-limit truncations (``info["TimeLimit.truncated"]``): a truncated
    episode is not a terminal state, its value target bootstraps from the real last observation (paper Sec. 4.1).

    :param dones: The dones of one step of the VecEnv
    :param infos: Its infos
    :return: The terminated and truncated flags
    """
    done_idx = np.flatnonzero(dones)
    truncated = np.zeros(len(dones), dtype=bool)
    if len(done_idx) == 0:  # most steps: nothing to sort out
        return np.asarray(dones, dtype=bool), truncated
    truncated[done_idx] = [infos[idx].get("TimeLimit.truncated", False) for idx in done_idx]
    return dones & ~truncated, truncated


def final_observations(
    obs: ArrayObs, ok: np.ndarray, infos: list[dict[str, Any]], env_indices: np.ndarray
) -> tuple[ArrayObs, np.ndarray]:
    """
    ``obs`` and ``ok`` with the rows of the envs cut by a time limit replaced by their real last observations, from
    SB3's ``info["terminal_observation"]``, sanitised.

    :param obs: The step's sanitised observations (after the resets)
    :param ok: Their validity
    :param infos: The infos of the step
    :param env_indices: The envs whose episode was truncated at that step
    """
    terminal = [infos[idx].get("terminal_observation") for idx in env_indices]
    if any(value is None for value in terminal):
        raise ValueError(
            "CGAC: the env reported a time-limit truncation (info['TimeLimit.truncated']) without "
            "info['terminal_observation'], which CGAC needs to bootstrap the value target. Use an SB3 VecEnv "
            "(DummyVecEnv, SubprocVecEnv) or one of sb3_cgac.vec_env's adapters, which provide it."
        )
    stacked: ArrayObs
    if isinstance(obs, dict):
        stacked = {key: np.stack([value[key] for value in terminal]) for key in obs}
        final: ArrayObs = {key: value.copy() for key, value in obs.items()}
    else:
        stacked, final = np.stack(terminal), obs.copy()
    stacked, stacked_ok = sanitize_observations(stacked)
    set_rows(final, env_indices, stacked)
    final_ok = ok.copy()
    final_ok[env_indices] = stacked_ok
    return final, final_ok


def _sanitize_array(obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if not np.issubdtype(obs.dtype, np.floating):
        return obs, np.ones(len(obs), dtype=bool)
    # A single comparison catches NaN (max is NaN, always False), +-Inf and huge values: in the common case one
    # reduction over the batch, then a row-wise check only when something is wrong (this runs at every env step)
    if np.abs(obs).max(initial=0.0) <= OBS_ABS_LIMIT:
        return obs.astype(np.float32, copy=False), np.ones(len(obs), dtype=bool)
    ok: np.ndarray = (np.abs(obs.reshape(len(obs), -1)) <= OBS_ABS_LIMIT).all(axis=1)
    obs = obs.astype(np.float32)  # a copy: the caller's array is left as it is
    obs[~ok] = 0
    return obs, ok


def _sanitize_tensor(obs: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    if not obs.is_floating_point():
        return obs, th.ones(len(obs), dtype=th.bool, device=obs.device)
    obs = obs.float()
    ok = (obs.abs() <= OBS_ABS_LIMIT).reshape(len(obs), -1).all(dim=1)
    return th.where(ok.reshape(-1, *([1] * (obs.dim() - 1))), obs, 0.0), ok
