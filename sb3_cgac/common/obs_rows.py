"""
Batches of one row per env: row operations on observations (one array or tensor, or a dict of them for a Dict
observation space), and the test of an info entry that holds one number per env.
"""

from typing import Any, overload

import numpy as np
import torch as th

TensorObs = th.Tensor | dict[str, th.Tensor]
ArrayObs = np.ndarray | dict[str, np.ndarray]


@overload
def rows(obs: th.Tensor, index: Any) -> th.Tensor: ...
@overload
def rows(obs: dict[str, th.Tensor], index: Any) -> dict[str, th.Tensor]: ...
@overload
def rows(obs: np.ndarray, index: Any) -> np.ndarray: ...
@overload
def rows(obs: dict[str, np.ndarray], index: Any) -> dict[str, np.ndarray]: ...
def rows(obs: Any, index: Any) -> Any:
    """The rows ``index`` (first dimension) of every entry."""
    if isinstance(obs, dict):
        return {key: value[index] for key, value in obs.items()}
    return obs[index]


def set_rows(obs: TensorObs | ArrayObs, index: Any, values: TensorObs | ArrayObs) -> None:
    """Write ``values`` (of the same kind as ``obs``) into the rows ``index`` of every entry, in place."""
    entries: dict[str, Any] = obs if isinstance(obs, dict) else {"": obs}
    new: dict[str, Any] = values if isinstance(values, dict) else {"": values}
    for key, value in entries.items():
        value[index] = new[key]


def where_rows(mask: th.Tensor, chosen: TensorObs, other: TensorObs) -> TensorObs:
    """Row by row (first dimension, or the first ``mask.dim()``), ``chosen`` where ``mask`` is True, else ``other``."""

    def select(a: th.Tensor, b: th.Tensor) -> th.Tensor:
        return th.where(mask.reshape(*mask.shape, *([1] * (a.dim() - mask.dim()))), a, b)

    if isinstance(chosen, dict):
        assert isinstance(other, dict)
        return {key: select(value, other[key]) for key, value in chosen.items()}
    assert isinstance(other, th.Tensor)
    return select(chosen, other)


def per_env_numbers(value: Any, num_envs: int) -> bool:
    """Whether ``value`` (an info entry of a vector env) holds one number per env: shape (num_envs,), numbers."""
    if isinstance(value, th.Tensor):
        return tuple(value.shape) == (num_envs,) and value.dtype != th.bool
    array = np.asarray(value)
    return array.shape == (num_envs,) and np.issubdtype(array.dtype, np.number)
