"""
Reward scaling by the spread of the discounted returns (SimbaV2, Lee et al., 2025): each reward is divided by
``max(std(G), max|G| / RETURN_LIMIT)``, where ``G`` is each env's running discounted return, so that the critics'
targets sit in a fixed range whatever the task's reward scale, and a sparse reward that fires for the first time
cannot blow them up. And the scale of the Q-values in the actor's loss (TD-MPC2, Hansen et al., 2024): their running
5th-95th percentile range. Statistics stay on the device: no host sync per step.
"""

from collections.abc import Callable

import torch as th

from sb3_cgac.torch_layers import AllReduce, RunningObsNormalizer

# Scaled discounted returns stay within about +/- this (SimbaV2's G_max)
RETURN_LIMIT = 5.0
# Floor of the scale, so that an all-zero reward stream leaves rewards unchanged rather than dividing by zero
SCALE_EPS = 1e-4
# TD-MPC2's scale of the actor's Q: the range between these quantiles of a minibatch's Q, at least Q_SPREAD_MIN (TD-MPC2:
# 1 in its unscaled returns; here in scaled ones, where a solved HalfCheetah-v5's range falls to about 0.4), averaged
# into the running value at Q_SPREAD_RATE per update
Q_SPREAD_QUANTILES = (0.05, 0.95)
Q_SPREAD_MIN = 0.5
Q_SPREAD_RATE = 0.01


class ReturnScale:
    """
    Running statistics of every env's discounted return ``G_t = gamma * G_{t-1} + r_t`` (reset at episode ends) over
    all envs and steps seen (with data-parallel training, those of every rank): their mean and variance (the policy's
    running normaliser, merged batch by batch) and the largest ``|G|``. ``scale_rewards`` updates them with a step's
    rewards, then divides the rewards by the scale.

    :param gamma: Discount factor of the returns (the algorithm's)
    :param device: Device of the statistics (the rewards')
    """

    def __init__(self, gamma: float, device: th.device | str = "cpu"):
        self.gamma = gamma
        self.statistics = RunningObsNormalizer(()).to(device)
        self.max_abs = th.zeros((), device=device)
        self.returns: th.Tensor | None = None  # each env's running return; reset with the envs

    def to(self, device: th.device | str) -> "ReturnScale":
        """Move the statistics to ``device`` (a model loaded on another device)."""
        self.statistics = self.statistics.to(device)
        self.max_abs = self.max_abs.to(device)
        self.returns = None
        return self

    def reset_returns(self) -> None:
        """Forget the envs' running returns (new envs, or envs reset outside an episode end)."""
        self.returns = None

    def scale(self) -> th.Tensor:
        """:return: The current divisor of the rewards, a scalar on the device"""
        return th.maximum(self.statistics.var.sqrt(), self.max_abs / RETURN_LIMIT).clamp_min(SCALE_EPS)

    def scale_rewards(
        self,
        rewards: th.Tensor,
        dones: th.Tensor,
        all_reduce: AllReduce | None = None,
        all_max: AllReduce | None = None,
    ) -> th.Tensor:
        """
        Update the statistics with one step of every env, then scale its rewards.

        :param rewards: Rewards of the step, shape (n_envs,); non-finite ones are left out of the statistics (the window
            excludes them) and returned as they are
        :param dones: Whether each env's episode ended at this step (its return restarts at the next one)
        :param all_reduce: With data-parallel training, the sum over the ranks (``DataParallel.sum``)
        :param all_max: With data-parallel training, the maximum over the ranks (``DataParallel.max``): with both, every
            rank merges the returns of all ranks and divides by the same scale, as its critics' averaged gradients need
        :return: The rewards divided by the scale
        """
        finite = th.isfinite(rewards)
        if self.returns is None or self.returns.shape != rewards.shape:
            self.returns = th.zeros_like(rewards)
        returns = self.gamma * self.returns + th.where(finite, rewards, 0.0)
        self.statistics.update(returns, finite, all_reduce)
        step_max = th.where(finite, returns.abs(), 0.0).max()
        self.max_abs = th.maximum(self.max_abs, step_max if all_max is None else all_max(step_max))
        self.returns = th.where(dones.to(returns.device), 0.0, returns)
        return th.where(finite, rewards / self.scale(), rewards)

    def __getstate__(self) -> dict:
        # Saved with the model: the statistics, not the envs' running returns
        state = self.__dict__.copy()
        state["returns"] = None
        return state


def weighted_quantiles(values: th.Tensor, weights: th.Tensor, quantiles: tuple[float, ...]) -> th.Tensor:
    """
    Quantiles of ``values`` under non-negative ``weights``: for each ``q``, the smallest value at which the weights of
    the values at or below it reach ``q`` of all the weights; on the device (no host sync).

    :param values: A batch of values, shape (B,)
    :param weights: Their weights, shape (B,) (boolean or float; zero leaves a value out)
    :param quantiles: The quantiles, each in [0, 1]
    :return: One value per quantile, shape (len(quantiles),)
    """
    order = th.argsort(values)
    cumulative = th.cumsum(weights[order].float(), dim=0)
    levels = th.tensor(quantiles, dtype=cumulative.dtype, device=values.device) * cumulative[-1]
    index = th.searchsorted(cumulative, levels).clamp_max(len(values) - 1)
    return values[order][index]


class QSpread:
    """
    The running scale of the Q-values in the actor's loss (TD-MPC2's ``RunningScale``): the 5th-95th percentile range
    of each minibatch's Q, at least 0.5, averaged at a rate of 0.01 per update. Dividing Q by it makes a fixed alpha
    weigh the entropy against the spread of Q: more when the critics tell states far apart, less when they do not.

    :param device: Device of the statistics (the critics')
    """

    def __init__(self, device: th.device | str = "cpu"):
        self.value = th.ones((), device=device)

    def to(self, device: th.device | str) -> "QSpread":
        """Move the statistics to ``device`` (a model loaded on another device)."""
        self.value = self.value.to(device)
        return self

    @th.no_grad()
    def update(
        self, q_values: th.Tensor, weights: th.Tensor, average: Callable[[th.Tensor], th.Tensor] | None = None
    ) -> th.Tensor:
        """
        Merge a minibatch's Q-values into the running scale.

        :param q_values: The Q-values the actor's loss reads, shape (B,)
        :param weights: Their weights (0 for excluded transitions)
        :param average: With data-parallel training, the mean over the ranks, so that every rank holds the same scale
        :return: The updated scale (a scalar on the device)
        """
        low, high = weighted_quantiles(q_values.float(), weights, Q_SPREAD_QUANTILES)
        spread = (high - low).clamp_min(Q_SPREAD_MIN)
        if average is not None:
            spread = average(spread)
        self.value.lerp_(spread, Q_SPREAD_RATE)
        return self.value
