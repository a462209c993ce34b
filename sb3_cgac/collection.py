"""
From an env step to the window's tensors: observations sanitised and on the policy's device, SB3's ``dones`` split
into terminations and time-limit truncations, and the real terminal observations that a truncated step's value
target bootstraps from (paper Sec. 4.1), for SB3 VecEnvs (NumPy, ``info["terminal_observation"]``) and torch-native
envs (``sb3_cgac.vec_env.TorchVecEnv``, device tensors).
"""

from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import torch as th
from stable_baselines3.common.utils import obs_as_tensor

from sb3_cgac.obs_rows import TensorObs, set_rows, where_rows

if TYPE_CHECKING:
    from sb3_cgac.vec_env.torch_vec_env import TensorStep

NumpyObs = np.ndarray | dict[str, np.ndarray]

# Observations with a larger magnitude are treated as corrupt, as in the paper's code
OBS_ABS_LIMIT = 1e6


class TerminalObservations(NamedTuple):
    """Real last observations of the envs whose episode was cut by a time limit at one step."""

    env_indices: th.Tensor
    observations: TensorObs
    ok: th.Tensor


class EnvStep(NamedTuple):
    """
    One step of every env as the window stores it: NumPy flags and rewards from an SB3 VecEnv, device tensors from a
    torch-native env (no host sync).
    """

    observations: TensorObs  # sanitised, on the device, after the reset of the envs that finished
    obs_ok: np.ndarray | th.Tensor  # which rows were usable before sanitising
    rewards: np.ndarray | th.Tensor
    dones: np.ndarray | th.Tensor
    terminated: np.ndarray | th.Tensor  # the episode ended in a terminal state
    truncated: np.ndarray | th.Tensor  # a time limit cut the episode: its value target bootstraps
    # The real last observations of the truncated envs: ``TerminalObservations`` (SB3 VecEnvs), or every env's
    # final observation and its validity (torch-native envs, of which the truncated rows count); None if none
    terminal: TerminalObservations | tuple[TensorObs, th.Tensor] | None
    infos: list[dict[str, Any]] | dict[str, Any]

    def bootstrap_observations(self) -> TensorObs:
        """The observations the next actions of this step are drawn at (paper Sec. 4.1)."""
        return bootstrap_observations(self.observations, self.truncated, self.terminal)


def vec_env_step(
    new_obs: Any, rewards: np.ndarray, dones: np.ndarray, infos: list[dict[str, Any]], device: th.device
) -> EnvStep:
    """One step of an SB3 VecEnv (``VecEnv.step``'s return values, SB3's episode contract) as the window stores it."""
    terminated, truncated, terminal = split_episode_ends(dones, infos, device)
    obs, ok = observations_to_tensor(new_obs, device)
    return EnvStep(obs, ok, rewards, dones, terminated, truncated, terminal, infos)


def tensor_env_step(step: "TensorStep", device: th.device) -> EnvStep:
    """One step of a torch-native env (``TorchVecEnv.step_tensors``) as the window stores it, on ``device``."""
    obs, obs_ok = tensor_observations(step.observations, device)
    terminal = tensor_observations(step.final_observations, device)
    terminated, truncated = step.terminated.to(device), step.truncated.to(device)
    return EnvStep(obs, obs_ok, step.rewards.to(device), terminated | truncated, terminated, truncated, terminal, step.infos)


def tensor_observations(obs: TensorObs, device: th.device) -> tuple[TensorObs, th.Tensor]:
    """Observations of a torch-native env on ``device``, sanitised (see ``sanitize_tensor_observations``)."""
    return sanitize_tensor_observations(obs_to_device(obs, device))


def sanitize_observations(obs: NumpyObs) -> tuple[NumpyObs, np.ndarray]:
    """
    Find the envs whose observation holds NaN, Inf or values beyond ``OBS_ABS_LIMIT`` and zero them,
    so that no network ever sees them; the returned mask lets the buffer exclude those transitions.

    :param obs: Batched observations (one row per env), an array or a dict of arrays
    :return: The cleaned observations (float ones in float32, the precision of the networks and the buffer)
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


def obs_to_device(obs: TensorObs, device: th.device) -> TensorObs:
    if isinstance(obs, dict):
        return {key: value.to(device) for key, value in obs.items()}
    return obs.to(device)


def bootstrap_observations(
    obs: TensorObs, truncated: Any, terminal: TerminalObservations | tuple[TensorObs, th.Tensor] | None
) -> TensorObs:
    """
    The observations that a step's next actions are drawn at: ``obs``, except the real terminal observation where a
    time limit cut the episode (``terminal`` as ``CGACRolloutBuffer.add`` takes it).
    """
    if terminal is None:
        return obs
    if isinstance(terminal, TerminalObservations):
        copy = {key: value.clone() for key, value in obs.items()} if isinstance(obs, dict) else obs.clone()
        set_rows(copy, terminal.env_indices, terminal.observations)
        return copy
    return where_rows(truncated, terminal[0], obs)


def observations_to_tensor(obs: Any, device: th.device) -> tuple[TensorObs, np.ndarray]:
    """Sanitize a batch of numpy observations (see ``sanitize_observations``) and move it to ``device`` (no copy on CPU)."""
    obs, ok = sanitize_observations(obs)
    return obs_as_tensor(obs, device), ok


def split_episode_ends(
    dones: np.ndarray, infos: list[dict[str, Any]], device: th.device
) -> tuple[np.ndarray, np.ndarray, TerminalObservations | None]:
    """
    Split SB3's ``dones`` into terminations and time-limit truncations (``info["TimeLimit.truncated"]``): a truncated
    episode is not a terminal state, its value target bootstraps from the real last observation (paper Sec. 4.1).

    :param dones: The dones of one step of the VecEnv
    :param infos: Its infos
    :param device: Device of the buffer
    :return: The terminated and truncated flags, and the terminal observations of the truncated envs (None if none)
    """
    done_idx = np.flatnonzero(dones)
    if len(done_idx) == 0:  # most steps: nothing to sort out
        return dones, dones, None
    truncated = np.zeros(len(dones), dtype=bool)
    truncated[done_idx] = [infos[idx].get("TimeLimit.truncated", False) for idx in done_idx]
    trunc_idx = np.flatnonzero(truncated)
    terminal = terminal_observations(infos, trunc_idx, device) if len(trunc_idx) > 0 else None
    return dones & ~truncated, truncated, terminal


def terminal_observations(infos: list[dict[str, Any]], env_indices: np.ndarray, device: th.device) -> TerminalObservations:
    """
    The real last observations of the envs cut by a time limit, from SB3's ``info["terminal_observation"]``.

    :param infos: The infos of one step of the VecEnv
    :param env_indices: The envs whose episode was truncated at that step
    :param device: Device of the buffer
    """
    terminal = [infos[idx].get("terminal_observation") for idx in env_indices]
    if any(obs is None for obs in terminal):
        raise ValueError(
            "CGAC: the env reported a time-limit truncation (info['TimeLimit.truncated']) without "
            "info['terminal_observation'], which CGAC needs to bootstrap the value target. Use an SB3 VecEnv "
            "(DummyVecEnv, SubprocVecEnv) or one of sb3_cgac.vec_env's adapters, which provide it."
        )
    stacked: Any
    if isinstance(terminal[0], dict):
        stacked = {key: np.stack([obs[key] for obs in terminal]) for key in terminal[0]}
    else:
        stacked = np.stack(terminal)
    obs, ok = observations_to_tensor(stacked, device)
    return TerminalObservations(th.as_tensor(env_indices, device=device), obs, th.as_tensor(ok, device=device))


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
