"""
CGAC in rl-baselines3-zoo: the algorithm registered, this package's YAML files, schedules and env backends, and
``build_model``, which builds a model from an entry as ``python -m sb3_cgac.train`` does.
"""

import argparse
import contextlib
import functools
import importlib
import importlib.resources
import importlib.util
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import gymnasium as gym
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.utils import ConstantSchedule, LinearSchedule
from stable_baselines3.common.vec_env import VecEnv

from sb3_cgac import CGAC
from sb3_cgac.common.distributed import world
from sb3_cgac.vec_env import BACKENDS, make_vec_env, register_backend_task, register_optional_envs
from sb3_cgac.vec_env.wrappers import RandomFirstEpisodeLength

try:
    import rl_zoo3.enjoy
    import rl_zoo3.exp_manager
    import rl_zoo3.train
    from rl_zoo3.exp_manager import ExperimentManager
    from rl_zoo3.utils import ALGOS, SimpleLinearSchedule
except ImportError as error:  # pragma: no cover - depends on the installed extras
    raise ImportError(f"sb3_cgac.zoo needs rl_zoo3 and its dependencies: pip install 'sb3_cgac[zoo]' ({error}).") from error

HYPERPARAMS_DIR = Path(str(importlib.resources.files("sb3_cgac.hyperparams")))
# Backends that are not built from per-env constructors, so the zoo's own make_vec_env cannot build them
ADAPTER_BACKENDS = ("envpool", "gymnasium", "gymnasium_async", "gymnasium_torch", "playground", "mjlab")
# Keys turned into schedules (the zoo's own)
SCHEDULE_KEYS = ("learning_rate", "clip_range", "clip_range_vf", "delta_std")


def parse_schedule(key: str, value: str) -> Callable[[float], float]:
    """
    A schedule named in a YAML entry: ``lin_<initial>`` (the zoo's, to 0 at the end of training) or
    ``lin_<start>_<end>_<end_fraction>`` (SB3's ``LinearSchedule``).
    """
    name, *numbers = value.split("_")
    try:
        values = [float(number) for number in numbers]
    except ValueError:
        values = []
    if name == "lin" and len(values) == 1:
        return SimpleLinearSchedule(values[0])
    if name == "lin" and len(values) == 3 and 0.0 < values[2] <= 1.0:
        return LinearSchedule(*values)
    raise ValueError(
        f"Unknown schedule {value!r} for {key}: use a number, 'lin_<initial value>' (linear to 0) or "
        "'lin_<start>_<end>_<end_fraction>' (linear from start to end over that fraction of n_timesteps, end_fraction "
        "in (0, 1]), e.g. 'lin_2e-3_1e-4_0.256'."
    )


def register() -> None:
    """
    Register CGAC in rl_zoo3 (and rsl_rl's PPO as ``rsl_ppo`` when ``rsl-rl-lib`` is installed), and the envs of
    gymnasium-robotics and MyoSuite when they are installed.
    """
    ALGOS["cgac"] = CGAC
    if importlib.util.find_spec("rsl_rl") is not None:
        from sb3_cgac.rsl_rl import RslPPO

        ALGOS["rsl_ppo"] = RslPPO
    register_optional_envs()


def algorithm_of(file: str) -> str:
    """
    The algorithm of a hyperparameter file's name: the name up to the first ``_`` (``ppo_parallel``: ppo), except
    for the algorithms whose names hold one (``rsl_ppo``, ``rsl_ppo_go1``: rsl_ppo).
    """
    for name in ("rsl_ppo",):
        if file == name or file.startswith(f"{name}_"):
            return name
    return file.split("_")[0]


def hyperparams_file(algo: str) -> Path | None:
    """This package's YAML file for ``algo`` (cgac, ppo, sac), or None to use the zoo's own."""
    path = HYPERPARAMS_DIR / f"{algo}.yml"
    return path if path.exists() else None


@contextlib.contextmanager
def swapped_attribute(owner: Any, name: str, value: Any) -> Iterator[None]:
    original = getattr(owner, name)
    setattr(owner, name, value)
    try:
        yield
    finally:
        setattr(owner, name, original)


class CGACExperimentManager(ExperimentManager):
    """
    rl_zoo3's ``ExperimentManager`` with three additions: ``backend`` builds the training and evaluation envs with
    ``sb3_cgac.vec_env.make_vec_env`` (the zoo's normalization, frame stacking and VecEnv wrappers still apply),
    schedules also take the form ``lin_<start>_<end>_<end_fraction>`` (SB3's ``LinearSchedule``: linear from start to
    end over that fraction of ``n_timesteps``, then constant; the authors' learning-rate decay), and the YAML key
    ``random_first_episode: true`` cuts the first episode of every training env at a random length (with any backend;
    evaluation envs are left alone).

    :param backend: One of ``sb3_cgac.vec_env.BACKENDS``
    :param backend_kwargs: Keyword arguments of the backend (e.g. ``num_threads`` for envpool)
    """

    def __init__(self, *args: Any, backend: str = "dummy", backend_kwargs: dict[str, Any] | None = None, **kwargs: Any):
        if backend not in BACKENDS:
            raise ValueError(f"Unknown --vec-env {backend!r}; choose one of {BACKENDS}.")
        if backend in ADAPTER_BACKENDS:
            kwargs["vec_env_type"] = "dummy"
        elif "vec_env_type" not in kwargs:
            kwargs["vec_env_type"] = backend
        # The zoo looks the id up in gymnasium's registry: envpool's, Playground's and mjlab's own tasks are not there
        register_backend_task(args[2] if len(args) > 2 else kwargs["env_id"], backend)
        super().__init__(*args, **kwargs)
        self.backend = backend
        self.backend_kwargs = backend_kwargs or {}
        self.random_first_episode = False

    def _preprocess_hyperparams(self, hyperparams: dict[str, Any]) -> Any:
        # An env setting, not a model argument
        self.random_first_episode = bool(hyperparams.pop("random_first_episode", False))
        result = super()._preprocess_hyperparams(hyperparams)
        world_size = world()[1]
        if world_size > 1:  # under torchrun, n_timesteps counts the env steps of all ranks together
            self.n_timesteps //= world_size
        return result

    @staticmethod
    def _preprocess_schedules(hyperparams: dict[str, Any]) -> dict[str, Any]:
        for key in SCHEDULE_KEYS:
            value = hyperparams.get(key)
            if isinstance(value, str):
                hyperparams[key] = parse_schedule(key, value)
            elif isinstance(value, (float, int)) and value >= 0:
                hyperparams[key] = ConstantSchedule(float(value))
        return hyperparams

    def create_envs(self, n_envs: int, eval_env: bool = False, no_log: bool = False) -> VecEnv:
        cut_first_episodes = self.random_first_episode and not eval_env
        if self.backend in ADAPTER_BACKENDS:
            make = functools.partial(self._make_adapter_vec_env, random_first_episode=cut_first_episodes)
            with swapped_attribute(rl_zoo3.exp_manager, "make_vec_env", make):
                return super().create_envs(n_envs, eval_env, no_log)
        if not cut_first_episodes:
            return super().create_envs(n_envs, eval_env, no_log)
        wrapper = self.env_wrapper

        def wrap(env: gym.Env) -> gym.Env:
            return RandomFirstEpisodeLength(wrapper(env) if wrapper is not None else env)

        with swapped_attribute(self, "env_wrapper", wrap):
            return super().create_envs(n_envs, eval_env, no_log)

    def _make_adapter_vec_env(
        self,
        env_fn: Callable,
        n_envs: int = 1,
        seed: int | None = None,
        env_kwargs: dict | None = None,
        random_first_episode: bool = False,
        **kwargs: Any,
    ) -> VecEnv:
        # Same signature as SB3's make_vec_env, which the zoo calls; the backend builds the envs by id instead
        if kwargs.get("wrapper_class") is not None:
            raise ValueError(
                f"The {self.backend} backend builds its envs by id and cannot apply the YAML's env_wrapper "
                f"({kwargs['wrapper_class']}); use --vec-env dummy or subproc for this entry."
            )
        return make_vec_env(
            self.env_name.gym_id,
            n_envs=n_envs,
            backend=self.backend,
            seed=seed,
            env_kwargs=env_kwargs,
            vec_env_kwargs=self.backend_kwargs,
            random_first_episode=random_first_episode,
        )


def build_model(
    algo: str,
    env_id: str,
    seed: int = 0,
    backend: str = "dummy",
    backend_kwargs: dict[str, Any] | None = None,
    log_folder: str = "logs",
    conf_file: str | None = None,
    hyperparams: dict[str, Any] | None = None,
    n_timesteps: int = 0,
    device: str = "auto",
    verbose: int = 0,
) -> tuple[BaseAlgorithm, CGACExperimentManager]:
    """
    Build a model from a YAML entry exactly as ``python -m sb3_cgac.train`` does (same preprocessing, envs,
    normalization and callbacks), without training it.

    :param algo: Algorithm key (cgac, ppo, sac, or any rl_zoo3 algorithm)
    :param env_id: Env id; the YAML entry of that id is used
    :param seed: Seed
    :param backend: Vec-env backend (``sb3_cgac.vec_env.BACKENDS``)
    :param backend_kwargs: Keyword arguments of the backend (e.g. ``num_threads`` for envpool)
    :param log_folder: Where the zoo writes the run's config and logs
    :param conf_file: YAML file (default: this package's file for ``algo``, else the zoo's)
    :param hyperparams: Overrides of the YAML entry (like the zoo's ``-params``)
    :param n_timesteps: Overrides the entry's ``n_timesteps`` when > 0
    :param device: Torch device
    :param verbose: Verbosity of the model
    :return: The model, and the experiment manager (its ``callbacks`` are the entry's callbacks to pass to learn)
    """
    register()
    conf = conf_file or hyperparams_file(algo)
    args = argparse.Namespace(algo=algo, env=env_id, seed=seed, vec_env=backend, conf_file=conf)
    manager = CGACExperimentManager(
        args,
        algo,
        env_id,
        log_folder,
        n_timesteps=n_timesteps,
        eval_freq=-1,
        hyperparams=hyperparams,
        seed=seed,
        verbose=verbose,
        device=device,
        config=None if conf is None else str(conf),
        backend=backend,
        backend_kwargs=backend_kwargs,
    )
    result = manager.setup_experiment()
    assert result is not None
    return result[0], manager
