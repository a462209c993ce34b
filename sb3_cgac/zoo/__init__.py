"""
rl-baselines3-zoo integration (extra ``zoo``): CGAC registered as ``rl_zoo3.ALGOS["cgac"]``, this package's
hyperparameter files as the default configuration, and the vectorised-env backends of ``sb3_cgac.vec_env``
behind the zoo's ``--vec-env`` flag (``envpool``, ``gymnasium``, ``gymnasium_async`` and the torch-native
``gymnasium_torch``, ``playground``, ``mjlab`` besides ``dummy`` and ``subproc``).

The package: ``manager`` registers CGAC, reads the YAML entries and builds models (``build_model``); ``cli`` holds the
commands ``train`` and ``enjoy`` behind ``python -m sb3_cgac.train`` and ``python -m sb3_cgac.enjoy``.
"""

from sb3_cgac.zoo.cli import enjoy, train
from sb3_cgac.zoo.manager import (
    HYPERPARAMS_DIR,
    CGACExperimentManager,
    algorithm_of,
    build_model,
    hyperparams_file,
    parse_schedule,
    register,
)

__all__ = [
    "HYPERPARAMS_DIR",
    "CGACExperimentManager",
    "algorithm_of",
    "build_model",
    "enjoy",
    "hyperparams_file",
    "parse_schedule",
    "register",
    "train",
]
