"""The mean of the adapters' episode statistics over finished episodes (their ``episode_info``)."""

from collections.abc import Iterable
from typing import Any

import numpy as np

# The entries of Monitor's episode dicts; the others are the adapters' episode_info statistics
MONITOR_KEYS = ("r", "l", "t")


def episode_metrics(episodes: Iterable[dict[str, Any]]) -> dict[str, float]:
    """
    Mean over ``episodes`` (an ``ep_info_buffer``) of every statistic beside Monitor's return, length and time:
    the ``episode_info`` of the envpool and gymnasium adapters, e.g. the reward components ``reward_*``.
    """
    values: dict[str, list[float]] = {}
    for episode in episodes:
        for key, value in episode.items():
            if key not in MONITOR_KEYS and isinstance(value, int | float | np.number):
                values.setdefault(key, []).append(float(value))
    return {key: float(np.mean(found)) for key, found in values.items()}
