"""
Schedules of the target-entropy coefficient beta (target entropy ``-beta * |A|``, paper Eq. 12-13), as SB3 callbacks.

They work with any algorithm that has a ``target_entropy_beta`` attribute read at every update (``CGAC``).
Use them from Python (``model.learn(..., callback=RewardEntropySchedule(...))``) or from a zoo YAML entry
(``callback: - sb3_cgac.callbacks.RewardEntropySchedule: {beta_final: 3.5}``).
"""

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback


class EntropyScheduleCallback(BaseCallback):
    """
    Base class: moves ``model.target_entropy_beta`` linearly from ``beta_init`` to ``beta_final``
    as a progress measure, defined by subclasses, goes from 0 to 1.

    :param beta_init: beta at the start (0.2 in the paper)
    :param beta_final: beta at the end (3.5 for Ant and SNU humanoid, 7.5 for Humanoid, 5 for AllegroHand)
    :param verbose: Verbosity level
    """

    def __init__(self, beta_init: float = 0.2, beta_final: float = 3.5, verbose: int = 0):
        super().__init__(verbose)
        self.beta_init = beta_init
        self.beta_final = beta_final

    def _init_callback(self) -> None:
        if not hasattr(self.model, "target_entropy_beta"):
            raise TypeError(
                f"{type(self).__name__} sets the target-entropy coefficient `target_entropy_beta`, which "
                f"{type(self.model).__name__} does not have: use it with sb3_cgac.CGAC."
            )
        self._set_beta()

    def progress(self) -> float:
        """Fraction of the schedule done, clipped to [0, 1] by the caller."""
        raise NotImplementedError

    def _set_beta(self) -> None:
        fraction = float(np.clip(self.progress(), 0.0, 1.0))
        beta = self.beta_init + fraction * (self.beta_final - self.beta_init)
        self.model.target_entropy_beta = beta  # type: ignore[attr-defined]
        self.logger.record("train/beta", beta)

    def _on_step(self) -> bool:
        self._set_beta()
        return True


class RewardEntropySchedule(EntropyScheduleCallback):
    """
    The paper's schedule (Eq. 13): beta follows the running average (EMA) of the per-step reward,
    from ``beta_init`` at ``init_expected_reward`` to ``beta_final`` at ``peak_expected_reward``
    (clipped to that range). The reward is the mean over envs of the unnormalized reward when
    the env is wrapped in ``VecNormalize``. With a torch-native env (``TorchVecEnv``) the average stays on the
    env's device and beta is set at the end of each rollout, before the updates that read it: one host read per
    rollout instead of one per step.

    :param beta_init: beta at (and below) the initial expected reward
    :param beta_final: beta at (and beyond) the peak expected reward
    :param init_expected_reward: Rough per-step reward of the initial policy (1.5 in the paper's code)
    :param peak_expected_reward: Rough per-step reward of a good policy (7.5 in the paper's code)
    :param ema: Smoothing of the running average (0.95 in the paper's code)
    :param verbose: Verbosity level
    """

    def __init__(
        self,
        beta_init: float = 0.2,
        beta_final: float = 3.5,
        init_expected_reward: float = 1.5,
        peak_expected_reward: float = 7.5,
        ema: float = 0.95,
        verbose: int = 0,
    ):
        super().__init__(beta_init, beta_final, verbose)
        if peak_expected_reward == init_expected_reward:
            raise ValueError(
                "RewardEntropySchedule needs peak_expected_reward != init_expected_reward "
                f"(both are {init_expected_reward}): set them to rough per-step rewards of a poor and a good policy."
            )
        if not 0.0 <= ema < 1.0:
            raise ValueError(f"RewardEntropySchedule: ema must be in [0, 1), got {ema}.")
        self.init_expected_reward = init_expected_reward
        self.peak_expected_reward = peak_expected_reward
        self.ema = ema
        # The paper's code starts the average at zero
        self.reward_average = 0.0
        self._device_average: th.Tensor | None = None  # the average of a torch-native env's rewards, on its device

    def progress(self) -> float:
        span = self.peak_expected_reward - self.init_expected_reward
        return (self.reward_average - self.init_expected_reward) / span

    def _on_step(self) -> bool:
        vec_normalize = self.model.get_vec_normalize_env()
        rewards = vec_normalize.get_original_reward() if vec_normalize is not None else self.locals["rewards"]
        if isinstance(rewards, th.Tensor):
            self._update_device_average(rewards)
            return True
        finite = np.asarray(rewards)[np.isfinite(rewards)]
        if finite.size > 0:
            self.reward_average = self.ema * self.reward_average + (1.0 - self.ema) * float(finite.mean())
        self.logger.record("train/reward_average", self.reward_average)
        return super()._on_step()

    def _update_device_average(self, rewards: th.Tensor) -> None:
        # The same average as the NumPy path's, computed without leaving the device (no host sync per step)
        if self._device_average is None:
            self._device_average = th.tensor(self.reward_average, dtype=th.float64, device=rewards.device)
        finite = th.isfinite(rewards)
        count = finite.sum()
        mean = th.where(finite, rewards, 0.0).sum(dtype=th.float64) / count.clamp_min(1)
        updated = self.ema * self._device_average + (1.0 - self.ema) * mean
        self._device_average = th.where(count > 0, updated, self._device_average)

    def _on_rollout_end(self) -> None:
        if self._device_average is not None:
            self.reward_average = self._device_average.item()
            self.logger.record("train/reward_average", self.reward_average)
            self._set_beta()


class ProgressEntropySchedule(EntropyScheduleCallback):
    """
    A schedule that needs no knowledge of the reward scale: beta moves linearly with training progress,
    reaching ``beta_final`` after ``end_fraction`` of ``learn()``'s ``total_timesteps``.

    :param beta_init: beta at the start of training
    :param beta_final: beta at the end of the schedule
    :param end_fraction: Fraction of training after which beta stays at ``beta_final``
    :param verbose: Verbosity level
    """

    def __init__(self, beta_init: float = 0.2, beta_final: float = 3.5, end_fraction: float = 1.0, verbose: int = 0):
        super().__init__(beta_init, beta_final, verbose)
        if not 0.0 < end_fraction <= 1.0:
            raise ValueError(f"ProgressEntropySchedule: end_fraction must be in (0, 1], got {end_fraction}.")
        self.end_fraction = end_fraction
        self.total_timesteps: int | None = None

    def _on_training_start(self) -> None:
        # learn()'s total, already shifted by the steps done before when reset_num_timesteps=False
        self.total_timesteps = self.locals.get("total_timesteps")
        self._set_beta()

    def progress(self) -> float:
        # Same progress measure as SB3's learning-rate schedules: num_timesteps / total_timesteps
        if not self.total_timesteps:
            return 0.0
        return self.num_timesteps / self.total_timesteps / self.end_fraction
