"""Exploration noise on the actions that the envs execute, apart from the policy's own entropy."""

from collections.abc import Iterable

import numpy as np
from stable_baselines3.common.noise import ActionNoise


class PerEnvNormalActionNoise(ActionNoise):
    """
    Gaussian action noise whose standard deviation differs from env to env: each env's is drawn uniformly from
    ``[std_min, std_max]`` at the start and again when its episode ends, so that the envs of one batch explore at many
    scales at once (FastTD3's exploration). Draws from NumPy's global generator, which the model's seed seeds.

    :param n_envs: Number of envs
    :param action_dim: Dimension of the actions
    :param std_min: Smallest standard deviation, in the units of actions scaled to [-1, 1]
    :param std_max: Largest standard deviation
    """

    def __init__(self, n_envs: int, action_dim: int, std_min: float, std_max: float):
        if not 0 <= std_min <= std_max:
            raise ValueError(f"PerEnvNormalActionNoise: need 0 <= std_min <= std_max, got {std_min} and {std_max}.")
        super().__init__()
        self.n_envs, self.action_dim = n_envs, action_dim
        self.std_min, self.std_max = std_min, std_max
        self.stds = np.random.uniform(std_min, std_max, (n_envs, 1))

    def __call__(self) -> np.ndarray:
        return (np.random.standard_normal((self.n_envs, self.action_dim)) * self.stds).astype(np.float32)

    def reset(self, indices: Iterable[int] | None = None) -> None:
        """Draw new standard deviations for the envs ``indices`` (all envs if None)."""
        rows = np.arange(self.n_envs) if indices is None else np.fromiter(indices, dtype=np.int64)
        self.stds[rows] = np.random.uniform(self.std_min, self.std_max, (len(rows), 1))

    def __repr__(self) -> str:
        return f"PerEnvNormalActionNoise(n_envs={self.n_envs}, std_min={self.std_min}, std_max={self.std_max})"
