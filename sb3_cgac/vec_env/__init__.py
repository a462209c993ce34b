"""
Vectorised-env backends for large numbers of parallel envs, all as Stable-Baselines3 ``VecEnv``:
SB3's ``DummyVecEnv`` and ``SubprocVecEnv``, ``EnvPoolVecEnv`` (C++ thread pool, extra ``envpool``),
``GymnasiumVecEnv`` over ``gymnasium.make_vec`` (sync or async), and ``TorchVecEnv`` over torch-native batched
simulators (tensors on a device, stepped by CGAC without NumPy: MuJoCo Playground, mjlab).

The package loads its modules on first use: the algorithm imports the one adapter module it needs
(``sb3_cgac.vec_env.torch_vec_env``), and ``envpool_vec_env``, ``gymnasium_vec_env``, ``playground_vec_env`` and
``mjlab_vec_env`` load only with their backend. ``make_vec_env`` (``factory``) builds any of them; ``wrappers`` holds
the gymnasium and VecEnv wrappers (``RandomFirstEpisodeLength``, ``VecObservationKeys``).
"""

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from sb3_cgac.vec_env.envpool_vec_env import EnvPoolVecEnv
    from sb3_cgac.vec_env.episodes import episode_metrics
    from sb3_cgac.vec_env.factory import BACKENDS, make_vec_env, register_backend_task, register_optional_envs
    from sb3_cgac.vec_env.gymnasium_vec_env import GymnasiumVecEnv, auto_episode_info
    from sb3_cgac.vec_env.torch_vec_env import NumpyToTorchVectorEnv, TensorStep, TorchVecEnv

# Each public name and the module that defines it
_MODULES = {
    "BACKENDS": "factory",
    "make_vec_env": "factory",
    "register_backend_task": "factory",
    "register_optional_envs": "factory",
    "episode_metrics": "episodes",
    "EnvPoolVecEnv": "envpool_vec_env",
    "GymnasiumVecEnv": "gymnasium_vec_env",
    "auto_episode_info": "gymnasium_vec_env",
    "NumpyToTorchVectorEnv": "torch_vec_env",
    "TensorStep": "torch_vec_env",
    "TorchVecEnv": "torch_vec_env",
}

__all__ = [
    "BACKENDS",
    "EnvPoolVecEnv",
    "GymnasiumVecEnv",
    "NumpyToTorchVectorEnv",
    "TensorStep",
    "TorchVecEnv",
    "auto_episode_info",
    "episode_metrics",
    "make_vec_env",
    "register_backend_task",
    "register_optional_envs",
]


def __getattr__(name: str) -> Any:
    if name in _MODULES:
        return getattr(importlib.import_module(f"sb3_cgac.vec_env.{_MODULES[name]}"), name)
    raise AttributeError(f"module 'sb3_cgac.vec_env' has no attribute {name!r}")
