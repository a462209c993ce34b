"""
Reward scaling by the spread of the discounted returns (SimbaV2, Lee et al., 2025): each reward is divided by
``max(std(G), max|G| / RETURN_LIMIT)``, where ``G`` is each env's running discounted return, so that the critics'
targets sit in a fixed range whatever the task's reward scale, and a sparse reward that fires for the first time
cannot blow them up. Statistics stay on the device: no host sync per step.
"""

import torch as th

from sb3_cgac.torch_layers import AllReduce, RunningObsNormalizer

# Scaled discounted returns stay within about +/- this (SimbaV2's G_max)
RETURN_LIMIT = 5.0
# Floor of the scale, so that an all-zero reward stream leaves rewards unchanged rather than dividing by zero
SCALE_EPS = 1e-4


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
