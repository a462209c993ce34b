"""
CGAC's hyperparameter rules: the checks of what a user passes, and how the paper's values (given for 4096 parallel
envs) become the values used at another number of envs. Pure functions, so that scripts use the same rules.
"""

import math
import warnings
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces

# The paper's minibatch size, used when the window holds that many transitions
PAPER_BATCH_SIZE = 4096
# The paper's Polyak coefficients tau_Q and tau_pi, one update of each per 4096 new transitions (4096 envs, one
# actor update per env step)
PAPER_TAU, PAPER_POLICY_TAU = 0.005, 0.001
PAPER_TRANSITIONS_PER_ACTOR_UPDATE = 4096
# Fewer parallel envs than this gives CGAC too little state diversity (paper Sec. 4.2 and Fig. 3a-b)
FEW_ENVS = 16
# critic_updates_per_step=None: FEW_ENVS_CRITIC_UPDATES below MANY_ENVS envs (a step of few envs brings little new
# data, and with the paper's 2 the bare defaults learned Pendulum-v1 more slowly and ended one of ten seeds in a dip);
# from MANY_ENVS envs on, enough updates that each collected transition is sampled at least SAMPLES_PER_TRANSITION
# times (updates * batch_size / n_envs), never fewer than the paper's 2: with the paper's batch of 4096 that is the
# paper's 2 at 1024 envs, 4 at 2048 and 8 at 4096, where the paper's 2 left Pendulum-v1 unlearned (docs/tuning.md)
MANY_ENVS = 1024
PAPER_CRITIC_UPDATES = 2
FEW_ENVS_CRITIC_UPDATES = 4
SAMPLES_PER_TRANSITION = 8
# Clamps of the learned entropy coefficient (see CGAC's ``ent_coef_monotone``)
ENT_COEF_CLAMPS = (True, False, "above_target")
# Precision of the networks in the updates ("auto": see ``resolve_update_precision``)
UPDATE_PRECISIONS = ("auto", "float32", "bfloat16")
# Regression losses of the critics (see ``sb3_cgac.losses.q_regression_loss``)
CRITIC_LOSSES = ("huber", "mse")


def positive_int(name: str, value: Any) -> None:
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
        raise ValueError(f"CGAC: {name} must be an integer >= 1, got {value!r}.")


def check_schedule(n_steps: int, buffer_window: int, critic_updates_per_step: int | None, policy_delay: int) -> None:
    """Check the counts of CGAC's iteration; each error says what is wrong and how to fix it."""
    for name, value in (("n_steps", n_steps), ("buffer_window", buffer_window), ("policy_delay", policy_delay)):
        positive_int(name, value)
    if critic_updates_per_step is not None:
        positive_int("critic_updates_per_step", critic_updates_per_step)
    if n_steps > buffer_window:
        raise ValueError(
            f"CGAC: n_steps ({n_steps}) is larger than buffer_window ({buffer_window}): each iteration writes n_steps "
            "new steps per env into a window of buffer_window steps. Lower n_steps or raise buffer_window "
            "(n_steps == buffer_window gives a fresh buffer every rollout)."
        )


def check_rates(
    tau: float | None, policy_tau: float | None, gamma: float, gae_lambda: float, predict_tau: float | None = None
) -> None:
    for name, value in (("tau", tau), ("policy_tau", policy_tau), ("predict_tau", predict_tau)):
        if value is not None and not 0.0 < value <= 1.0:
            raise ValueError(f"CGAC: {name} must be in (0, 1] (1 turns the averaging off), got {value}.")
    if not 0.0 <= gamma <= 1.0 or not 0.0 <= gae_lambda <= 1.0:
        raise ValueError(f"CGAC: gamma and gae_lambda must be in [0, 1], got {gamma} and {gae_lambda}.")


def check_hyperparameters(
    *,
    n_steps: int,
    buffer_window: int,
    critic_updates_per_step: int | None,
    policy_delay: int,
    batch_size: int | None,
    gae_horizon: int | None,
    tau: float | None,
    policy_tau: float | None,
    gamma: float,
    gae_lambda: float,
    lr_decay_iterations: int,
    final_learning_rate: float | None,
    max_grad_norm: float | None,
    behaviour_kl_coef: float,
    ent_coef: str | float,
    ent_coef_monotone: bool | str,
    entropy_schedule: str | None,
    entropy_schedule_kwargs: dict[str, Any],
    entropy_schedules: tuple[str, ...],
    critic_loss: str,
    update_precision: str,
    compile_updates: Any,
    cuda_graphs: Any = False,
    clip_actor_gradient_outliers: bool = False,
    refresh_target_values: bool = False,
    predict_tau: float | None = None,
    decay_ent_coef_learning_rate: bool = False,
) -> None:
    """
    Check CGAC's constructor arguments that do not depend on the env (see ``CGAC`` for their meaning); each error
    says what is wrong and how to fix it.

    :param entropy_schedules: The names of the entropy schedules that ``entropy_schedule`` may take
    """
    check_schedule(n_steps, buffer_window, critic_updates_per_step, policy_delay)
    for name, value in (("batch_size", batch_size), ("gae_horizon", gae_horizon)):
        if value is not None:
            positive_int(name, value)
    check_rates(tau, policy_tau, gamma, gae_lambda, predict_tau)
    positive_int("lr_decay_iterations", lr_decay_iterations)
    if final_learning_rate is not None and not final_learning_rate >= 0:
        raise ValueError(f"CGAC: final_learning_rate must be >= 0 or None (no decay), got {final_learning_rate}.")
    if max_grad_norm is not None and max_grad_norm <= 0:
        raise ValueError(f"CGAC: max_grad_norm must be > 0, got {max_grad_norm}.")
    if not behaviour_kl_coef >= 0:
        raise ValueError(f"CGAC: behaviour_kl_coef must be >= 0 (0 turns the penalty off), got {behaviour_kl_coef}.")
    learn_alpha, _ = parse_ent_coef(ent_coef)
    if not isinstance(decay_ent_coef_learning_rate, bool):
        raise ValueError(f"CGAC: decay_ent_coef_learning_rate must be True or False, got {decay_ent_coef_learning_rate!r}.")
    if decay_ent_coef_learning_rate and (final_learning_rate is None or not learn_alpha):
        raise ValueError(
            "CGAC: decay_ent_coef_learning_rate=True follows the decay of the actor's learning rate and scales a learned "
            f"alpha's rate, but final_learning_rate={final_learning_rate} and ent_coef={ent_coef!r}; set "
            "final_learning_rate (e.g. 1e-4) and ent_coef='auto', or leave decay_ent_coef_learning_rate=False."
        )
    check_choice(
        "ent_coef_monotone",
        ent_coef_monotone,
        ENT_COEF_CLAMPS,
        ": True is the paper's clamp (alpha never increases), 'above_target' holds alpha only while the entropy is "
        "at or above its target, False leaves it free",
    )
    check_choice("entropy_schedule", entropy_schedule, (*entropy_schedules, None), " (None: a fixed beta)")
    if entropy_schedule is None and entropy_schedule_kwargs:
        raise ValueError("CGAC: entropy_schedule_kwargs is given but entropy_schedule is None; set entropy_schedule.")
    check_choice("critic_loss", critic_loss, CRITIC_LOSSES)
    check_choice("update_precision", update_precision, UPDATE_PRECISIONS)
    if not isinstance(compile_updates, (bool, dict)):
        raise ValueError(
            f"CGAC: compile_updates must be True, False or a dict of torch.compile keyword arguments, got {compile_updates!r}."
        )
    if not isinstance(refresh_target_values, bool):
        raise ValueError(f"CGAC: refresh_target_values must be True or False, got {refresh_target_values!r}.")
    check_cuda_graphs(cuda_graphs, compile_updates, clip_actor_gradient_outliers)


def with_predict_actor(policy_kwargs: dict[str, Any], predict_tau: float | None) -> dict[str, Any]:
    """
    The policy keyword arguments with ``predict_actor`` set as ``predict_tau`` requires: the policy keeps the
    copy of the actor that ``predict()`` acts with exactly when CGAC averages one.

    :param policy_kwargs: The policy keyword arguments given by the user (or loaded with a model)
    :param predict_tau: CGAC's ``predict_tau``
    :return: The policy keyword arguments, with ``predict_actor`` when ``predict_tau`` is given
    """
    wanted = predict_tau is not None
    given = policy_kwargs.get("predict_actor", wanted)
    if given != wanted:
        raise ValueError(
            f"CGAC: policy_kwargs has predict_actor={given!r} but predict_tau is {predict_tau!r}: the copy of the actor "
            "that predict() acts with is averaged at the rate predict_tau. Remove predict_actor from policy_kwargs "
            "and set predict_tau (None: predict() acts with the averaged actor)."
        )
    return {**policy_kwargs, "predict_actor": True} if wanted else policy_kwargs


def check_cuda_graphs(cuda_graphs: Any, compile_updates: Any, clip_actor_gradient_outliers: bool) -> None:
    """``cuda_graphs`` is a bool, and not combined with the options whose steps cannot be captured as they are."""
    if not isinstance(cuda_graphs, bool):
        raise ValueError(f"CGAC: cuda_graphs must be True or False, got {cuda_graphs!r}.")
    if cuda_graphs and compile_updates:
        raise ValueError(
            "CGAC: cuda_graphs=True and compile_updates cannot be combined; choose one (for torch.compile's own CUDA "
            "graphs, compile_updates=dict(mode='reduce-overhead'))."
        )
    if cuda_graphs and clip_actor_gradient_outliers:
        raise ValueError(
            "CGAC: cuda_graphs=True does not support clip_actor_gradient_outliers=True (its running average is "
            "replaced at every step); turn one of them off."
        )


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


def check_choice(name: str, value: Any, choices: tuple[Any, ...], hint: str = "") -> None:
    # `is` as well as ==, so that True does not match 1 and "above_target" is not confused with True
    if not any(value is choice or (type(value) is type(choice) and value == choice) for choice in choices):
        raise ValueError(f"CGAC: unknown {name} {value!r}; choose one of {choices}{hint}.")


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


def resolve_batch_size(batch_size: int | None, buffer_window: int, n_envs: int) -> int:
    """
    :param batch_size: The requested minibatch size (None: the paper's 4096, or the whole window if smaller)
    :return: The minibatch size; an error if the window cannot hold it
    """
    capacity = buffer_window * n_envs
    if batch_size is None:
        return min(PAPER_BATCH_SIZE, capacity)
    if batch_size > capacity:
        raise ValueError(
            f"CGAC: batch_size ({batch_size}) is larger than the buffer, which holds buffer_window * n_envs "
            f"= {buffer_window} * {n_envs} = {capacity} transitions. Lower batch_size or raise buffer_window or "
            "the number of envs (batch_size=None picks min(4096, buffer size))."
        )
    return batch_size


def resolve_critic_updates_per_step(critic_updates_per_step: int | None, n_envs: int, batch_size: int) -> int:
    """
    :param critic_updates_per_step: The requested critic updates per collected step (None: the rule below)
    :param n_envs: The number of parallel envs
    :param batch_size: The resolved minibatch size
    :return: The given count, or for None: 4 below ``MANY_ENVS`` envs; from there on the smallest count (at least
        the paper's 2) that samples each collected transition ``SAMPLES_PER_TRANSITION`` times on average
    """
    if critic_updates_per_step is not None:
        return critic_updates_per_step
    if n_envs < MANY_ENVS:
        return FEW_ENVS_CRITIC_UPDATES
    return max(PAPER_CRITIC_UPDATES, math.ceil(SAMPLES_PER_TRANSITION * n_envs / batch_size))


def scaled_polyak_rates(
    tau: float | None, policy_tau: float | None, n_envs: int, policy_delay: int, critic_updates_per_step: int
) -> tuple[float, float]:
    """
    The Polyak coefficients applied at every actor update. Given values are kept; None scales the paper's tau_Q and
    tau_pi, meant for 4096 new transitions per update, to the ``m = n_envs * policy_delay / critic_updates_per_step``
    transitions per actor update here: ``1 - (1 - tau_paper) ** sqrt(4096 / m)``.

    At 64 envs the paper's per-update rates make the averaged copies lag a third of a 200k-step run; the same rate per
    transition made training unstable; the square root sits in between (docs/tuning.md).
    """
    transitions = n_envs * policy_delay / critic_updates_per_step
    exponent = float(np.sqrt(PAPER_TRANSITIONS_PER_ACTOR_UPDATE / transitions))
    resolved_tau = tau if tau is not None else 1.0 - (1.0 - PAPER_TAU) ** exponent
    resolved_policy_tau = policy_tau if policy_tau is not None else 1.0 - (1.0 - PAPER_POLICY_TAU) ** exponent
    return resolved_tau, resolved_policy_tau


def decayed_learning_rate(
    learning_rate: float, final_learning_rate: float | None, iterations: int, decay_iterations: int
) -> float:
    """The authors' linear decay from ``learning_rate`` to ``final_learning_rate`` over ``decay_iterations``."""
    if final_learning_rate is None:
        return learning_rate
    fraction = min(1.0, iterations / decay_iterations)
    return learning_rate + fraction * (final_learning_rate - learning_rate)


def warn_many_critic_updates(critic_updates_per_step: int | None, n_envs: int, batch_size: int | None, resolved: int) -> None:
    """
    Warn when ``critic_updates_per_step=None`` resolves to more updates per step than the paper's batch would need,
    because the ``batch_size`` the user gave is small for the number of envs (at the user's constructor call).
    """
    if critic_updates_per_step is not None or batch_size is None or batch_size >= PAPER_BATCH_SIZE:
        return
    if resolved > resolve_critic_updates_per_step(None, n_envs, PAPER_BATCH_SIZE):
        warnings.warn(
            f"CGAC: critic_updates_per_step=None resolves to {resolved} critic updates per env step at n_envs={n_envs} "
            f"with batch_size={batch_size}, so that each collected transition is sampled {SAMPLES_PER_TRANSITION} times "
            "on average; every step then costs that many updates. Raise batch_size (the paper's 4096, or None) or set "
            "critic_updates_per_step (the paper's 2).",
            UserWarning,
            stacklevel=3,
        )


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
