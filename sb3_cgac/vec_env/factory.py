"""``make_vec_env``: one function for every backend of ``sb3_cgac.vec_env``, and the registration of the envs some
backends bring."""

import contextlib
import functools
from typing import Any

import gymnasium as gym
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.env_util import make_vec_env as sb3_make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv

from sb3_cgac.vec_env.envpool_vec_env import EnvPoolVecEnv
from sb3_cgac.vec_env.gymnasium_vec_env import GymnasiumVecEnv
from sb3_cgac.vec_env.torch_vec_env import NumpyToTorchVectorEnv, TorchVecEnv
from sb3_cgac.vec_env.wrappers import RandomFirstEpisodeLength

BACKENDS = ("dummy", "subproc", "envpool", "gymnasium", "gymnasium_async", "gymnasium_torch", "playground", "mjlab")


def register_optional_envs() -> None:
    """Register the envs of gymnasium-robotics (Adroit, ...) and MyoSuite (myo*) when they are installed."""
    with contextlib.suppress(ImportError):
        import gymnasium_robotics

        gym.register_envs(gymnasium_robotics)
    with contextlib.suppress(ImportError):
        import myosuite  # noqa: F401  (registers the myo* envs on import)


def register_backend_task(env_id: str, backend: str) -> None:
    """
    Register a task that only ``backend`` builds in gymnasium's registry under its id, for tools that look ids up there
    (rl_zoo3): envpool's tasks that gymnasium lacks (``"envpool"``: MuJoCo Playground's ports, e.g.
    ``Go1JoystickFlatTerrain-v1``), Playground's JAX tasks (``"playground"``, e.g. ``CheetahRun``) and mjlab's
    (``"mjlab"``). The registered env only explains which backend builds the task; ids that gymnasium already has, and
    the other backends, are left alone.
    """
    if backend in ("envpool", "playground", "mjlab") and env_id not in gym.registry:
        gym.register(env_id, entry_point=functools.partial(_backend_only_task, env_id, backend))


def _backend_only_task(env_id: str, backend: str, **kwargs: Any) -> gym.Env:
    raise gym.error.Error(
        f"{env_id} is a {backend} task without a gymnasium env: build it with the {backend} backend "
        f"(sb3_cgac.vec_env.make_vec_env({env_id!r}, n_envs, backend={backend!r}), or --vec-env {backend})."
    )


def _make_registered(env_id: str, **kwargs: Any) -> gym.Env:
    """
    ``gym.make`` in a fresh worker process, where only the envs registered on import exist; like SB3's
    ``make_vec_env`` for an id, it asks for ``render_mode="rgb_array"`` unless told otherwise or the env refuses it.
    """
    register_optional_envs()
    if "render_mode" not in kwargs:
        with contextlib.suppress(TypeError):
            return gym.make(env_id, render_mode="rgb_array", **kwargs)
    return gym.make(env_id, **kwargs)


def make_vec_env(
    env_id: str,
    n_envs: int = 1,
    backend: str = "dummy",
    seed: int | None = None,
    env_kwargs: dict[str, Any] | None = None,
    vec_env_kwargs: dict[str, Any] | None = None,
    random_first_episode: bool = True,
) -> VecEnv:
    """
    Build ``n_envs`` copies of ``env_id`` as an SB3 ``VecEnv`` with the chosen backend. Every backend gives
    Monitor episode statistics (``rollout/ep_rew_mean``), ``terminal_observation`` and ``TimeLimit.truncated``.

    :param env_id: Registered gymnasium id (an envpool task id for ``backend="envpool"``)
    :param n_envs: Number of parallel envs
    :param backend: ``"dummy"`` (SB3 DummyVecEnv: one process), ``"subproc"`` (SB3 SubprocVecEnv: a process per
        env), ``"envpool"`` (one C++ thread pool, the fastest for MuJoCo), ``"gymnasium"`` / ``"gymnasium_async"``
        (``gymnasium.make_vec`` in sync or async mode), ``"gymnasium_torch"`` (the sync one seen as a torch-native
        env, ``TorchVecEnv``: CGAC's path for GPU simulators, here on the CPU), ``"playground"`` (a MuJoCo Playground
        task in JAX, ``PlaygroundVectorEnv`` as a ``TorchVecEnv``: extra ``playground``; ``vec_env_kwargs`` ``impl``,
        ``episode_length``, ``config_overrides``), ``"mjlab"`` (an mjlab task on MuJoCo Warp, ``MjlabVectorEnv`` as a
        ``TorchVecEnv``: extra ``mjlab``; ``vec_env_kwargs`` ``device``, ``clip_actions``, ``episode_length_s``)
    :param seed: Seed of the envs (env i gets ``seed + i``)
    :param env_kwargs: Keyword arguments of the env constructor
    :param vec_env_kwargs: Keyword arguments of the backend (e.g. ``num_threads`` for envpool,
        ``start_method`` for subproc, ``info_keys`` and ``episode_info`` for the envpool and gymnasium adapters)
    :param random_first_episode: Cut the first episode of every env at a random length (a time-limit truncation,
        not reported as an episode), so that the envs do not all reset at the same steps: with envs in step, CGAC's
        window periodically holds only initial states and its critic forgets the rest
        (``sb3_cgac.vec_env.wrappers.RandomFirstEpisodeLength`` for SB3's VecEnvs, the adapters' own
        ``random_first_episode`` for the others). Evaluation envs do not need it
    :return: The vectorised env
    """
    env_kwargs = env_kwargs or {}
    vec_env_kwargs = vec_env_kwargs or {}
    if backend in ("dummy", "subproc"):
        vec_env_cls = DummyVecEnv if backend == "dummy" else SubprocVecEnv
        return sb3_make_vec_env(
            env_id if backend == "dummy" else functools.partial(_make_registered, env_id),
            n_envs=n_envs,
            seed=seed,
            env_kwargs=env_kwargs,
            vec_env_cls=vec_env_cls,
            vec_env_kwargs=vec_env_kwargs,
            wrapper_class=RandomFirstEpisodeLength if random_first_episode else None,
        )
    if backend in ("playground", "mjlab"):  # torch-native simulators, imported only when asked for
        if backend == "playground":
            from sb3_cgac.vec_env.playground_vec_env import PlaygroundVectorEnv as venv_class
        else:
            from sb3_cgac.vec_env.mjlab_vec_env import MjlabVectorEnv as venv_class  # type: ignore[assignment]
        simulator = venv_class(env_id, n_envs, **vec_env_kwargs, **env_kwargs)
        tensor_env = TorchVecEnv(simulator, random_first_episode=random_first_episode)
        if seed is not None:
            tensor_env.seed(seed)
        return tensor_env
    vec_env_kwargs = {**vec_env_kwargs, "random_first_episode": random_first_episode}
    if backend == "envpool":
        return EnvPoolVecEnv(env_id, n_envs, seed=seed if seed is not None else 0, **vec_env_kwargs, **env_kwargs)
    if backend in ("gymnasium", "gymnasium_async", "gymnasium_torch"):
        venv = gym.make_vec(
            gym.spec(env_id),  # the spec's entry point also works in async workers, where the id may not be registered
            num_envs=n_envs,
            vectorization_mode="async" if backend == "gymnasium_async" else "sync",
            vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP},
            **env_kwargs,
        )
        if backend == "gymnasium_torch":
            vec_env: VecEnv = TorchVecEnv(NumpyToTorchVectorEnv(venv), **vec_env_kwargs)
        else:
            vec_env = GymnasiumVecEnv(venv, **vec_env_kwargs)
        if seed is not None:
            vec_env.seed(seed)
        return vec_env
    raise ValueError(f"Unknown vec-env backend {backend!r}; choose one of {BACKENDS}.")
