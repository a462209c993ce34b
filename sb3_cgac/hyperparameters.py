"""
CGAC's hyperparameter rules: the checks of what a user passes, and what ``"auto"`` resolves to on each device, as
functions of their arguments, so that scripts use the same rules.

``"auto"`` depends on where the updates run. On a CPU an update costs in proportion to its batch, so the defaults are
the update cost of the MuJoCo entries (batch 512, 4 critic updates per step, Polyak rates 0.02 and 0.05). On a GPU a
batch of 4096 costs about what one of 512 does, so the defaults are the paper's batch, with the update count and the
Polyak rates adapted to the number of envs.
"""

import inspect
import math
import warnings
from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnv

# The paper's minibatch size
PAPER_BATCH_SIZE = 4096
# The paper's Polyak coefficients tau_Q and tau_pi, one update of each per 4096 new transitions (4096 envs, one actor
# update per env step)
PAPER_TAU, PAPER_POLICY_TAU = 0.005, 0.001
PAPER_TRANSITIONS_PER_ACTOR_UPDATE = 4096
PAPER_CRITIC_UPDATES = 2
# CPU defaults: the update cost and the averaging of the MuJoCo entries (hyperparams/cgac.yml)
CPU_BATCH_SIZE = 512
CPU_CRITIC_UPDATES = 4
CPU_TAU, CPU_POLICY_TAU = 0.02, 0.05
# GPU defaults of the update count: 4 below MANY_ENVS envs (a step of few envs brings little new data); from there on
# enough updates that each collected transition is sampled SAMPLES_PER_TRANSITION times (updates * batch / n_envs),
# never fewer than the paper's 2 (docs/tuning.md, "Device-dependent update cost")
MANY_ENVS = 1024
FEW_ENVS_CRITIC_UPDATES = 4
SAMPLES_PER_TRANSITION = 8
# Fewer parallel envs than this gives CGAC too little state diversity (paper Sec. 4.2 and Fig. 3a-b)
FEW_ENVS = 16
# Clamps of the learned entropy coefficient (see CGAC's ``ent_coef_monotone``)
ENT_COEF_CLAMPS = (True, False, "above_target")
# Precision of the networks in the updates ("auto": see ``resolve_update_precision``)
UPDATE_PRECISIONS = ("auto", "float32", "bfloat16")
# gamma="auto": the discount from the episodes' time limit (TD-MPC2's rule), within this range; without a time limit
# the paper's 0.99
HORIZON_GAMMA_RANGE = (0.95, 0.995)
DEFAULT_GAMMA = 0.99


def positive_int(name: str, value: Any) -> None:
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
        raise ValueError(f"CGAC: {name} must be an integer >= 1, got {value!r}.")


def _auto_or(name: str, value: Any, check: Any) -> None:
    if value is None:
        raise ValueError(f"CGAC: {name}=None is the spelling of sb3_cgac 0.1.0; pass {name}='auto' (or a value).")
    if value != "auto":
        check(name, value)


def _rate(name: str, value: Any, other: str = "'auto'") -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 < value <= 1.0:
        raise ValueError(f"CGAC: {name} must be {other} or in (0, 1] (1 turns the averaging off), got {value!r}.")


def check_choice(name: str, value: Any, choices: tuple[Any, ...], hint: str = "") -> None:
    # `is` as well as ==, so that True does not match 1 and "above_target" is not confused with True
    if not any(value is choice or (type(value) is type(choice) and value == choice) for choice in choices):
        raise ValueError(f"CGAC: unknown {name} {value!r}; choose one of {choices}{hint}.")


def check_hyperparameters(
    *,
    n_steps: int,
    buffer_window: int,
    policy_delay: int,
    batch_size: int | str,
    critic_updates_per_step: int | str,
    tau: float | str,
    policy_tau: float | str,
    gae_horizon: int | None,
    predict_tau: float | None,
    predict_actor: bool | None,
    gamma: float | str,
    gae_lambda: float,
    max_grad_norm: float | None,
    ent_coef: str | float,
    ent_coef_monotone: bool | str,
    critic_loss: str,
    update_precision: str,
    cuda_graphs: bool,
) -> None:
    """
    Check the constructor arguments of ``CGAC`` that do not depend on the env (see ``CGAC`` for their meaning); each
    error says what is wrong and how to fix it.

    :param predict_actor: The ``predict_actor`` of the policy_kwargs, if given (None: not given)
    """
    for name, value in (("n_steps", n_steps), ("buffer_window", buffer_window), ("policy_delay", policy_delay)):
        positive_int(name, value)
    if n_steps > buffer_window:
        raise ValueError(
            f"CGAC: n_steps ({n_steps}) is larger than buffer_window ({buffer_window}): each iteration "
            "writes n_steps new steps per env into a window of buffer_window steps. Lower n_steps or raise "
            "buffer_window (n_steps == buffer_window gives a fresh buffer every rollout)."
        )
    _auto_or("batch_size", batch_size, positive_int)
    _auto_or("critic_updates_per_step", critic_updates_per_step, positive_int)
    _auto_or("tau", tau, _rate)
    _auto_or("policy_tau", policy_tau, _rate)
    if gae_horizon is not None:
        positive_int("gae_horizon", gae_horizon)
    if predict_tau is not None:
        _rate("predict_tau", predict_tau, "None")
    if predict_actor is not None and predict_actor != (predict_tau is not None):
        raise ValueError(
            f"CGAC: policy_kwargs has predict_actor={predict_actor!r} but predict_tau is {predict_tau!r}: the copy "
            "of the actor that predict() acts with is averaged at the rate predict_tau. Remove predict_actor from "
            "policy_kwargs and set predict_tau (None: predict() acts with the averaged actor)."
        )
    if isinstance(gamma, str) and gamma != "auto":
        raise ValueError(f"CGAC: gamma must be a number in [0, 1] or 'auto' (from the episodes' time limit), got {gamma!r}.")
    if not 0.0 <= (DEFAULT_GAMMA if gamma == "auto" else gamma) <= 1.0 or not 0.0 <= gae_lambda <= 1.0:  # type: ignore[operator]
        raise ValueError(f"CGAC: gamma and gae_lambda must be in [0, 1], got {gamma} and {gae_lambda}.")
    if max_grad_norm is not None and max_grad_norm <= 0:
        raise ValueError(f"CGAC: max_grad_norm must be > 0, got {max_grad_norm}.")
    parse_ent_coef(ent_coef)
    check_choice(
        "ent_coef_monotone",
        ent_coef_monotone,
        ENT_COEF_CLAMPS,
        ": True is the paper's clamp (alpha never increases), 'above_target' holds alpha only while the entropy is "
        "at or above its target, False leaves it free",
    )
    check_choice("critic_loss", critic_loss, ("huber", "mse"))
    check_choice("update_precision", update_precision, UPDATE_PRECISIONS)
    if not isinstance(cuda_graphs, bool):
        raise ValueError(f"CGAC: cuda_graphs must be True or False, got {cuda_graphs!r}.")


def episode_horizon(env: VecEnv | None) -> int | None:
    """
    :param env: A vector env (SB3's, or one of ``sb3_cgac.vec_env``'s adapters, possibly wrapped)
    :return: The time limit of its episodes: the adapters' ``max_episode_steps()``, else the spec of its first env;
        None when it has none
    """
    if env is None:
        return None
    limit = getattr(env, "max_episode_steps", None)  # the adapters (VecEnvWrapper forwards the lookup)
    if callable(limit):
        try:
            limit = limit()
        except ValueError:  # the adapters raise when the spec has no time limit
            limit = None
    if limit is None:
        try:
            spec = env.get_attr("spec", [0])[0]
        except (AttributeError, IndexError):
            spec = None
        limit = getattr(spec, "max_episode_steps", None)
    return int(limit) if limit else None


def horizon_gamma(horizon: int | None) -> float:
    """
    The discount from the episode length ``T`` as TD-MPC2 sets it for all its tasks: ``(T/5 - 1) / (T/5)`` clipped to
    [0.95, 0.995], i.e. an effective horizon of a fifth of the episode (0.975 for 200 steps, 0.995 from 1,000);
    ``DEFAULT_GAMMA`` when the episodes have no time limit.
    """
    if horizon is None:
        return DEFAULT_GAMMA
    effective = horizon / 5
    return float(min(max((effective - 1) / effective, HORIZON_GAMMA_RANGE[0]), HORIZON_GAMMA_RANGE[1]))


# The constructor arguments of CGAC that check_hyperparameters takes (by name)
CHECKED_ARGUMENTS = tuple(name for name in inspect.signature(check_hyperparameters).parameters if name != "predict_actor")


def parse_ent_coef(ent_coef: str | float) -> tuple[bool, float]:
    """
    :param ent_coef: A float for a fixed alpha, ``"auto"`` or ``"auto_<init>"`` for a learned one
    :return: whether alpha is learned, and its initial value
    """
    if isinstance(ent_coef, str):
        if ent_coef == "auto":
            return True, 1.0
        if ent_coef.startswith("auto_"):
            try:
                init_value = float(ent_coef[len("auto_") :])
            except ValueError:
                init_value = -1.0
            if init_value > 0:
                return True, init_value
        raise ValueError(
            f"CGAC: malformed ent_coef {ent_coef!r}; use a float, 'auto', or 'auto_<init>' with init > 0 "
            "(e.g. 'auto_0.1', the paper's initial alpha)."
        )
    if float(ent_coef) < 0:
        raise ValueError(f"CGAC: ent_coef must be >= 0, got {ent_coef}.")
    return False, float(ent_coef)


def check_action_space(action_space: spaces.Space | None) -> None:
    """CGAC's actor is a tanh-squashed Gaussian: it needs a bounded Box."""
    if not isinstance(action_space, spaces.Box):
        raise ValueError(
            f"CGAC only supports continuous (Box) action spaces, got {action_space}. For discrete actions use "
            "an algorithm such as PPO, A2C or DQN; for a discretised control problem, expose the continuous controls."
        )
    if not (np.all(np.isfinite(action_space.low)) and np.all(np.isfinite(action_space.high))):
        raise ValueError(
            f"CGAC squashes actions with tanh into the Box bounds, but the action space {action_space} is unbounded. "
            "Give the env finite bounds, e.g. with gymnasium.wrappers.RescaleAction or ClipAction."
        )


def resolve_batch_size(batch_size: int | str | None, buffer_window: int, n_envs: int, device: th.device) -> int:
    """
    :param batch_size: The requested minibatch size; ``"auto"``: 512 on a CPU, the paper's 4096 elsewhere, at most the
        window; None (models saved by sb3_cgac 0.1.0): min(4096, window)
    :return: The minibatch size (``check_batch_fits`` checks it against the window)
    """
    if batch_size is None or batch_size == "auto":
        wanted = CPU_BATCH_SIZE if batch_size == "auto" and device.type == "cpu" else PAPER_BATCH_SIZE
        return min(wanted, buffer_window * n_envs)
    assert isinstance(batch_size, int)
    return batch_size


def check_batch_fits(batch_size: int, buffer_window: int, n_envs: int) -> None:
    """
    An error that says what to change if the window cannot hold a minibatch (at construction, and before training: a
    model loaded with fewer envs still predicts).
    """
    capacity = buffer_window * n_envs
    if batch_size > capacity:
        raise ValueError(
            f"CGAC: batch_size ({batch_size}) is larger than the buffer, which holds buffer_window * n_envs "
            f"= {buffer_window} * {n_envs} = {capacity} transitions. Lower batch_size or raise buffer_window or "
            "the number of envs (batch_size='auto' never takes more than the buffer; a loaded model keeps its batch: "
            "set model.batch_size)."
        )


def resolve_critic_updates_per_step(updates: int | str | None, n_envs: int, batch_size: int, device: th.device) -> int:
    """
    :param updates: The requested critic updates per collected step; ``"auto"``: 4 on a CPU; elsewhere, and for
        None (models saved by sb3_cgac 0.1.0), 4 below ``MANY_ENVS`` envs, from there on the smallest count (at least
        the paper's 2) that samples each collected transition ``SAMPLES_PER_TRANSITION`` times on average
    :param n_envs: The number of parallel envs
    :param batch_size: The resolved minibatch size
    """
    if isinstance(updates, int):
        return updates
    if updates == "auto" and device.type == "cpu":
        return CPU_CRITIC_UPDATES
    if n_envs < MANY_ENVS:
        return FEW_ENVS_CRITIC_UPDATES
    return max(PAPER_CRITIC_UPDATES, math.ceil(SAMPLES_PER_TRANSITION * n_envs / batch_size))


def resolve_polyak_rates(
    tau: float | str | None,
    policy_tau: float | str | None,
    n_envs: int,
    policy_delay: int,
    critic_updates_per_step: int,
    device: th.device,
) -> tuple[float, float]:
    """
    The Polyak coefficients applied at every actor update. Given values are kept. ``"auto"`` on a CPU: 0.02 and 0.05
    (the MuJoCo entries'). Elsewhere, and for None (models saved by sb3_cgac 0.1.0), the paper's tau_Q and tau_pi,
    meant for 4096 new transitions per update, scaled to the ``m = n_envs * policy_delay / critic_updates_per_step``
    transitions per actor update here: ``1 - (1 - tau_paper) ** sqrt(4096 / m)``, between the paper's rate per update
    and its rate per transition (docs/tuning.md, "Device-dependent update cost").
    """
    transitions = n_envs * policy_delay / critic_updates_per_step
    exponent = float(np.sqrt(PAPER_TRANSITIONS_PER_ACTOR_UPDATE / transitions))
    on_cpu = device.type == "cpu"

    def resolve(value: float | str | None, cpu_value: float, paper_value: float) -> float:
        if isinstance(value, (int, float)):
            return float(value)
        if value == "auto" and on_cpu:
            return cpu_value
        return 1.0 - (1.0 - paper_value) ** exponent

    return resolve(tau, CPU_TAU, PAPER_TAU), resolve(policy_tau, CPU_POLICY_TAU, PAPER_POLICY_TAU)


class UpdateCost(NamedTuple):
    """The resolved update cost and averaging of a ``CGAC`` model."""

    batch_size: int
    critic_updates_per_step: int
    tau: float
    policy_tau: float


def resolve_auto_hyperparameters(
    batch_size: int | str | None,
    critic_updates_per_step: int | str | None,
    tau: float | str | None,
    policy_tau: float | str | None,
    *,
    n_envs: int,
    buffer_window: int,
    policy_delay: int,
    device: th.device,
) -> UpdateCost:
    """
    The numbers that ``"auto"`` (and 0.1.0's None) stand for on ``device`` with ``n_envs`` envs; given numbers are kept.
    """
    batch_size = resolve_batch_size(batch_size, buffer_window, n_envs, device)
    updates = resolve_critic_updates_per_step(critic_updates_per_step, n_envs, batch_size, device)
    tau, policy_tau = resolve_polyak_rates(tau, policy_tau, n_envs, policy_delay, updates, device)
    return UpdateCost(batch_size, updates, tau, policy_tau)


def native_bfloat16(device: th.device) -> bool:
    """
    Whether ``device`` is a CPU that multiplies bfloat16 matrices in hardware (AVX512-BF16 or AMX). Other CPUs
    emulate bfloat16, which is slower than float32; CUDA is left out: there eager bfloat16 updates were no faster.
    """
    if device.type != "cpu":
        return False
    try:  # private helpers of torch.cpu: a torch without them counts as no native bfloat16
        return bool(th.cpu._is_avx512_bf16_supported() or th.cpu._is_amx_tile_supported())
    except AttributeError:
        return False


def resolve_update_precision(update_precision: str, device: th.device) -> th.dtype | None:
    """
    The autocast dtype of the updates' networks: None for float32. ``"auto"`` takes bfloat16 where it is native
    (``native_bfloat16``), so that one configuration runs fast on such CPUs and in float32 elsewhere.
    """
    if update_precision == "bfloat16" or (update_precision == "auto" and native_bfloat16(device)):
        return th.bfloat16
    return None


def warn_few_envs(n_envs: int) -> None:
    """Warn that CGAC learns poorly from fewer than ``FEW_ENVS`` parallel envs (at the user's constructor call)."""
    if n_envs < FEW_ENVS:
        warnings.warn(
            f"CGAC is built for many parallel environments (the paper uses 4096) and learns poorly from few: "
            f"this model has n_envs={n_envs}. Use a vectorised env with more copies, e.g. "
            "make_vec_env(env_id, n_envs=64).",
            UserWarning,
            stacklevel=3,
        )
