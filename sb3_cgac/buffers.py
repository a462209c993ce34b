"""Rolling-window rollout buffer for CGAC, with Q-GAE(lambda) value targets (paper Eq. 9-10)."""

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import get_action_dim, get_obs_shape
from stable_baselines3.common.utils import get_device

from sb3_cgac.collection import EnvStep
from sb3_cgac.common.obs_rows import TensorObs, rows, where_rows

# Q-function used for the targets: (observations, actions) -> values of shape (batch,)
QFunction = Callable[[TensorObs, th.Tensor], th.Tensor]


class CGACSamples(NamedTuple):
    """A minibatch of the window: the update steps' input."""

    observations: TensorObs
    actions: th.Tensor
    returns: th.Tensor
    weights: th.Tensor


def _storage_dtype(space: spaces.Space) -> th.dtype:
    # Float observations are stored in float32 (MuJoCo gives float64); integer ones (images) keep their type
    if space.dtype is not None and np.issubdtype(space.dtype, np.floating):
        return th.float32
    return th.as_tensor(np.zeros(1, dtype=space.dtype)).dtype


def _flatten_obs(obs: TensorObs, n_leading: int) -> TensorObs:
    # Merge the first `n_leading` dimensions (time, env) into one batch dimension
    def flatten(value: th.Tensor) -> th.Tensor:
        return value.reshape(-1, *value.shape[n_leading:])

    if isinstance(obs, dict):
        return {key: flatten(value) for key, value in obs.items()}
    return flatten(obs)


def _write_row(storage: th.Tensor, index: int | slice, value: th.Tensor) -> None:
    # Runs several times per env step: on CPU a write through NumPy views of the same memory costs a fraction of torch's
    # indexing and dispatch (the first torch ops after a blocking env step are slow, their code is out of cache)
    if storage.device.type == "cpu" and value.device.type == "cpu":
        storage.numpy()[index] = value.numpy()
    else:
        storage[index] = value


def _nbytes(obs: TensorObs) -> int:
    values = obs.values() if isinstance(obs, dict) else [obs]
    return sum(value.element_size() * value.nelement() for value in values)


def _linear_recurrence(offsets: th.Tensor, decays: th.Tensor) -> th.Tensor:
    """
    Solve ``y_t = offsets_t + decays_t * y_{t+1}`` over the first dimension, ``y`` of the last step being its offset.

    A Hillis-Steele scan: ceil(log2(steps)) rounds of a few whole-window operations rather than a group of small ones
    per step, so that the kernel launches per iteration on a GPU do not grow with the window. After round k (from 0) a
    step holds the recurrence's terms of itself and the 2^(k+1) - 1 steps after it, and the product of their decays.
    """
    shift, n_steps = 1, offsets.shape[0]
    while shift < n_steps:
        offsets = th.cat([th.addcmul(offsets[:-shift], decays[:-shift], offsets[shift:]), offsets[-shift:]])
        if 2 * shift < n_steps:  # the decays are not read after the last round
            decays = th.cat([decays[:-shift] * decays[shift:], decays[-shift:]])
        shift *= 2
    return offsets


class CGACRolloutBuffer:
    """
    Rolling window of the last ``buffer_window`` steps of every env (time-major ring buffer).

    Per step and env it stores the observation, the (squashed) action, the reward, termination and
    truncation flags and the *next action*: a fresh sample of the averaged actor at the next observation,
    or at the real terminal observation for a time-limit truncation. The next observation is not stored
    again: it is the following step's observation, the ``current observation`` of the buffer for the newest
    step, or the real last observation of a truncated episode (kept, for every env, in a second array of the
    observations' size, allocated at the first truncation; only its truncated rows are read).

    Before the updates, :meth:`compute_returns` evaluates the min-of-twin target Q at (next observation, next
    action) for the steps added since its last call only (``Qbar``, computed once as in the paper's code), then
    the Q-GAE targets of the whole window (paper Eq. 9-10):
    ``Y_t = r_t + g m_t Qbar_{t+1} + sum_{k>=1} (g lam)^k [r_{t+k} + g m_{t+k} Qbar_{t+k+1} - Qbar_{t+k}]``,
    the sum being cut at episode ends, at the newest step of the window and after ``gae_horizon`` terms.
    Given a sampler of next actions, it draws the next actions and evaluates Qbar again for the whole window.

    :param buffer_window: Number of steps kept per env (32 in the paper)
    :param observation_space: Observation space
    :param action_space: Action space
    :param device: Device on which the data is stored and sampled
    :param n_envs: Number of parallel environments
    :param gamma: Discount factor
    :param gae_lambda: lambda of Q-GAE
    :param gae_horizon: Maximum number of reward terms in a target (None: the whole window)
    """

    def __init__(
        self,
        buffer_window: int,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        device: th.device | str = "auto",
        n_envs: int = 1,
        gamma: float = 0.99,
        gae_lambda: float = 0.95,
        gae_horizon: int | None = None,
    ):
        self.buffer_window = buffer_window
        self.observation_space = observation_space
        self.action_space = action_space
        self.device = get_device(device)
        self.n_envs = n_envs
        self.gamma = gamma
        self.gae_lambda = gae_lambda
        self.gae_horizon = gae_horizon
        self.action_dim = get_action_dim(action_space)
        self.reset()

    def _zeros_obs(self, leading: tuple[int, ...]) -> TensorObs:
        def zeros(space: spaces.Space) -> th.Tensor:
            return th.zeros((*leading, *get_obs_shape(space)), dtype=_storage_dtype(space), device=self.device)  # type: ignore[misc]

        if isinstance(self.observation_space, spaces.Dict):
            return {key: zeros(space) for key, space in self.observation_space.spaces.items()}
        return zeros(self.observation_space)

    def reset(self) -> None:
        """Empty the window (the storage is allocated once here and reused)."""
        shape = (self.buffer_window, self.n_envs)
        self.observations = self._zeros_obs(shape)
        self.actions = th.zeros((*shape, self.action_dim), device=self.device)
        self.next_actions = th.zeros((*shape, self.action_dim), device=self.device)
        self.rewards = th.zeros(shape, device=self.device)
        self.terminated = th.zeros(shape, dtype=th.bool, device=self.device)
        self.truncated = th.zeros(shape, dtype=th.bool, device=self.device)
        self.obs_ok = th.ones(shape, dtype=th.bool, device=self.device)
        self.reward_ok = th.ones(shape, dtype=th.bool, device=self.device)
        self.next_values = th.zeros(shape, device=self.device)
        self.returns = th.zeros(shape, device=self.device)
        # Whether each transition takes part in the losses (the sampled weight), 1 byte each
        self.weights = th.zeros(shape, dtype=th.bool, device=self.device)
        # Every env's final observation at the steps that hold truncations (only the truncated rows are read), so that
        # adding a step needs no host sync; allocated at the first such step
        self.final_observations: TensorObs | None = None
        self.final_obs_ok: th.Tensor | None = None
        # Observation of the envs now, i.e. the next observation of the newest step
        self.current_obs = self._zeros_obs((self.n_envs,))
        self.current_obs_ok = th.ones(self.n_envs, dtype=th.bool, device=self.device)
        self.pos = 0
        self.size = 0
        # Newest steps whose Qbar and validity are not computed yet
        self.n_pending = 0
        # Transitions with a non-finite or huge observation or reward since the last reset, counted on the device
        # without a host sync: read when the logs are written (the n_nonfinite property)
        self._n_nonfinite = th.zeros((), dtype=th.int64, device=self.device)

    @property
    def n_nonfinite(self) -> int:
        return int(self._n_nonfinite.item())

    @property
    def n_transitions(self) -> int:
        return self.size * self.n_envs

    @staticmethod
    def _write_obs(storage: TensorObs, index: int | slice, obs: TensorObs) -> None:
        if isinstance(storage, dict):
            assert isinstance(obs, dict)
            for key, value in storage.items():
                _write_row(value, index, obs[key])
        else:
            assert isinstance(obs, th.Tensor)
            _write_row(storage, index, obs)

    def set_current_obs(self, obs: TensorObs, obs_ok: th.Tensor) -> None:
        """
        Set the observation the next step starts from (after a reset of the envs).

        :param obs: Sanitized observations, one row per env
        :param obs_ok: Which rows were finite before sanitizing
        """
        self._write_obs(self.current_obs, slice(None), obs)
        _write_row(self.current_obs_ok, slice(None), obs_ok)

    def add(self, actions: th.Tensor, step: EnvStep, next_actions: th.Tensor) -> None:
        """
        Store one step of all envs; the step starts from the current observation, which becomes the step's observation.

        :param actions: Squashed actions taken, shape (n_envs, action_dim)
        :param step: What the envs gave (``sb3_cgac.collection``): rewards, flags, observations after the resets and
            the real last observations of the truncated episodes
        :param next_actions: Averaged-actor samples at the next observation, or at the real last observation
            for truncated envs, shape (n_envs, action_dim)
        """
        pos = self.pos
        rewards_ok = th.isfinite(step.rewards)
        rewards = th.where(rewards_ok, step.rewards, 0.0)
        excluded = ~rewards_ok | ~step.obs_ok
        if step.final_ok is not None:
            excluded |= step.truncated & ~step.final_ok
        self._n_nonfinite += excluded.sum()

        self._write_obs(self.observations, pos, self.current_obs)
        _write_row(self.obs_ok, pos, self.current_obs_ok)
        _write_row(self.actions, pos, actions)
        _write_row(self.next_actions, pos, next_actions)
        _write_row(self.rewards, pos, rewards)
        _write_row(self.reward_ok, pos, rewards_ok)
        _write_row(self.terminated, pos, step.terminated)
        _write_row(self.truncated, pos, step.truncated)
        if step.final_observations is not None:
            assert step.final_ok is not None
            self._write_final_observations(pos, step.final_observations, step.final_ok)
        self.set_current_obs(step.observations, step.obs_ok)

        self.pos = (pos + 1) % self.buffer_window
        self.size = min(self.size + 1, self.buffer_window)
        self.n_pending = min(self.n_pending + 1, self.buffer_window)

    def _write_final_observations(self, pos: int, final_obs: TensorObs, final_ok: th.Tensor) -> None:
        if self.final_observations is None:
            self.final_observations = self._zeros_obs((self.buffer_window, self.n_envs))
            self.final_obs_ok = th.ones((self.buffer_window, self.n_envs), dtype=th.bool, device=self.device)
        assert self.final_obs_ok is not None
        self._write_obs(self.final_observations, pos, final_obs)
        _write_row(self.final_obs_ok, pos, final_ok)

    def _chronological_slots(self, n_steps: int) -> th.Tensor:
        # Ring positions of the newest `n_steps` steps, oldest first
        return (self.pos - n_steps + th.arange(n_steps, device=self.device)) % self.buffer_window

    @th.no_grad()
    def compute_returns(self, target_q: QFunction, max_batch: int = 65536) -> None:
        """
        Evaluate Qbar for the steps added since the last call, then recompute the Q-GAE targets of the window.

        :param target_q: Min-of-twin target critic, ``(obs, actions) -> values``
        :param max_batch: Largest batch given to ``target_q`` at once (bounds the memory of the forward pass)
        """
        n_new = self.n_pending
        if n_new == 0:
            return
        slots = self._chronological_slots(n_new)
        # Next observations of the new steps: each following step's observation, the current one for the newest
        next_obs = rows(self.observations, slots[1:])
        if isinstance(next_obs, dict):
            assert isinstance(self.current_obs, dict)
            next_obs = {key: th.cat([value, self.current_obs[key][None]]) for key, value in next_obs.items()}
        else:
            assert isinstance(self.current_obs, th.Tensor)
            next_obs = th.cat([next_obs, self.current_obs[None]])
        next_ok = th.cat([self.obs_ok[slots[1:]], self.current_obs_ok[None]])
        # Time-limit truncations bootstrap from the real last observation (paper Sec. 4.1)
        if self.final_observations is not None:
            assert self.final_obs_ok is not None
            truncated = self.truncated[slots]
            next_obs = where_rows(truncated, rows(self.final_observations, slots), next_obs)
            next_ok = th.where(truncated, self.final_obs_ok[slots], next_ok)
        flat_obs = _flatten_obs(next_obs, 2)
        flat_actions = self.next_actions[slots].reshape(-1, self.action_dim)
        values = th.cat(
            [
                target_q(rows(flat_obs, slice(start, start + max_batch)), flat_actions[start : start + max_batch])
                for start in range(0, flat_actions.shape[0], max_batch)
            ]
        )
        self.next_values[slots] = values.reshape(n_new, self.n_envs)

        valid = self.obs_ok[slots] & self.reward_ok[slots] & (self.terminated[slots] | next_ok)
        self.weights[slots] = valid
        self.n_pending = 0
        self._compute_q_gae()

    def _compute_q_gae(self) -> None:
        order = self._chronological_slots(self.size)
        rewards, next_values = self.rewards[order], self.next_values[order]
        terminated = self.terminated[order]
        valid = self.weights[order]
        # The trace goes on into the next step unless the episode ended here, the next transition is
        # excluded, or this is the newest step of the window
        cont = ~(terminated | self.truncated[order])
        cont[:-1] &= valid[1:]
        cont[-1] = False
        gamma_lam = self.gamma * self.gae_lambda
        one_step = rewards + self.gamma * (~terminated) * next_values
        # Y_t = r_t + g m_t Qbar_{t+1} + g lam c_t (Y_{t+1} - Qbar_{t+1}) = a_t + b_t Y_{t+1}, with b = 0 at the newest step
        decay = gamma_lam * cont.to(rewards.dtype)
        returns = _linear_recurrence(one_step - decay * next_values, decay)

        horizon = self.gae_horizon
        if horizon is not None and horizon < self.size:
            # Cut after `horizon` terms: Y^h_t = Y_t - (g lam)^h C_{t,h} (Y_{t+h} - Qbar_{t+h}),
            # where C_{t,h} = 1 when the trace is not cut between t and t+h
            cuts = th.cumsum((~cont).int(), dim=0)
            cuts_before = th.cat([th.zeros_like(cuts[:1]), cuts[:-1]])
            no_cut = cuts[horizon - 1 : self.size - 1] == cuts_before[: self.size - horizon]
            tail = returns[horizon:] - next_values[horizon - 1 : self.size - 1]
            returns[: self.size - horizon] -= gamma_lam**horizon * no_cut * tail
        self.returns[order] = returns

    def sample(self, batch_size: int) -> CGACSamples:
        """
        Sample transitions uniformly (with replacement) from the window.

        :param batch_size: Number of transitions
        :return: Observations, actions, Q-GAE targets and weights (0 for excluded transitions)
        """
        idx = th.randint(0, self.n_transitions, (batch_size,), device=self.device)
        return CGACSamples(
            observations=rows(_flatten_obs(self.observations, 2), idx),
            actions=self.actions.view(-1, self.action_dim)[idx],
            returns=self.returns.view(-1)[idx],
            weights=self.weights.view(-1)[idx].float(),
        )

    def nbytes(self) -> int:
        """Memory held by the buffer, final observations included."""
        tensors = [self.actions, self.next_actions, self.rewards, self.terminated, self.truncated]
        tensors += [self.obs_ok, self.reward_ok, self.next_values, self.returns, self.weights, self.current_obs_ok]
        total = _nbytes(self.observations) + _nbytes(self.current_obs) + sum(_nbytes(t) for t in tensors)
        if self.final_observations is not None:
            total += _nbytes(self.final_observations)
        return total

    def raw_transition_nbytes(self) -> int:
        """Bytes of the transitions themselves: observation, action, next action, reward and two flags each."""
        per_step = _nbytes(rows(self.observations, 0)) + 2 * _nbytes(self.actions[0])
        per_step += _nbytes(self.rewards[0]) + _nbytes(self.terminated[0]) + _nbytes(self.truncated[0])
        return per_step * self.buffer_window
