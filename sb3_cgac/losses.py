"""
CGAC's loss functions, pure functions of tensors and networks (as sb3-contrib keeps ``quantile_huber_loss`` apart from
its algorithms).
"""

from collections.abc import Callable

import torch as th
from stable_baselines3.common.type_aliases import PyTorchObs

from sb3_cgac.policies import Actor, CGACCritic

# A concatenation over the ranks of data-parallel training (last dimension)
Gather = Callable[[th.Tensor], th.Tensor]


def q_regression_loss(
    q_values: th.Tensor, returns: th.Tensor, weights: th.Tensor, gather: Gather | None = None, loss: str = "huber"
) -> th.Tensor:
    """
    Sum over critics and batch of the per-sample regression loss of the critics to the Q-GAE targets (paper Eq. 8).

    :param q_values: Q-values of each critic, shape (n_critics, batch)
    :param returns: Q-GAE targets, shape (batch,)
    :param weights: Sample weights (0 for excluded transitions), shape (batch,)
    :param gather: With data-parallel training, the concatenation over the ranks (``DataParallel.gather``): the
        median is then that of every rank's minibatch, as one process with all of them would take it
    :param loss: ``"huber"``: the adaptive Huber loss of the paper's code, squared below 4x the batch median of
        ``|delta|`` of each critic and linear above (continuous at the threshold), so that a few huge target errors
        cannot dominate the update; ``"mse"``: the squared error everywhere (Eq. 8 as written)
    :return: The summed loss (divide by the weight sum for the mean)
    """
    delta = (q_values - returns) * weights
    if loss == "mse":
        return (delta**2).sum()
    abs_delta = delta.abs()
    batch = abs_delta.detach() if gather is None else gather(abs_delta.detach())
    threshold = 4.0 * batch.median(dim=-1, keepdim=True).values
    linear = 2.0 * threshold * abs_delta - threshold**2
    return th.where(abs_delta < threshold, delta**2, linear).sum()


def critic_loss(
    critic: CGACCritic,
    observations: PyTorchObs,
    actions: th.Tensor,
    returns: th.Tensor,
    weights: th.Tensor,
    weight_sum: th.Tensor,
    autocast_dtype: th.dtype | None = None,
    gather: Gather | None = None,
    loss: str = "huber",
) -> tuple[th.Tensor, th.Tensor]:
    """
    Weighted mean loss of all critics to the Q-GAE targets: the regression of paper Eq. 8 (see ``q_regression_loss``),
    or for categorical critics the cross-entropy to the targets' HL-Gauss distributions (``HistogramSupport``).

    :param critic: The trained critics
    :param observations: Observations of the minibatch
    :param actions: Actions taken
    :param returns: Q-GAE targets (paper Eq. 9-10)
    :param weights: Sample weights (0 for excluded transitions)
    :param weight_sum: Sum of the weights (at least 1)
    :param autocast_dtype: Run the networks under autocast to this dtype (e.g. ``th.bfloat16``); None: float32
    :param gather: With data-parallel training, the concatenation over the ranks (see ``q_regression_loss``)
    :param loss: The regression loss of scalar critics, ``"huber"`` or ``"mse"`` (see ``q_regression_loss``)
    :return: The loss, and the mean Q-value of the first critic (detached)
    """
    with th.autocast(actions.device.type, dtype=autocast_dtype or th.bfloat16, enabled=autocast_dtype is not None):
        outputs = critic.q_outputs(observations, actions)
    q_values = critic.q_values_from_outputs(outputs.float())
    if critic.support is None:
        total = q_regression_loss(q_values, returns, weights, gather, loss)
    else:
        total = (critic.support.cross_entropy(outputs, returns) * weights).sum()
    return total / weight_sum, q_values[0].detach().mean()


def actor_loss(
    actor: Actor,
    critic: CGACCritic,
    observations: PyTorchObs,
    weights: th.Tensor,
    weight_sum: th.Tensor,
    ent_coef: th.Tensor,
    autocast_dtype: th.dtype | None = None,
    q_reduction: str = "min",
) -> tuple[th.Tensor, th.Tensor]:
    """
    The actor loss of paper Eq. 7, ``E[alpha * log pi(a|s) - Q(s, a)]`` with reparameterised actions, where Q is the
    minimum of the critics (Eq. 11) or their mean. The critics' parameters should not require gradients: only dQ/da
    is needed.

    :param actor: The trained actor
    :param critic: The trained critics
    :param observations: Observations of the minibatch
    :param weights: Sample weights (0 for excluded transitions)
    :param weight_sum: Sum of the weights (at least 1)
    :param ent_coef: The entropy coefficient alpha (detached)
    :param autocast_dtype: Run the networks under autocast to this dtype (e.g. ``th.bfloat16``); None: float32
    :param q_reduction: How the actor reads the critics: ``"min"`` (paper Eq. 11) or ``"mean"``
    :return: The loss, and the log-probabilities of the sampled actions (detached)
    """
    with th.autocast(weights.device.type, dtype=autocast_dtype or th.bfloat16, enabled=autocast_dtype is not None):
        actions_pi, log_prob = actor.action_log_prob(observations)
        q_values = critic.q_values(observations, actions_pi).float()
    q_value = q_values.min(dim=0).values if q_reduction == "min" else q_values.mean(dim=0)
    log_prob = log_prob.float()
    loss = ((ent_coef * log_prob - q_value) * weights).sum() / weight_sum
    return loss, log_prob.detach()


def clamped_log_ent_coef(
    log_ent_coef: th.Tensor, previous: th.Tensor, entropy_gap: th.Tensor, mode: bool | str = "above_target"
) -> th.Tensor:
    """
    The clamp of the learned entropy coefficient after its update (paper Sec. 4.2: ``alpha = min(alpha_prev, alpha_new)``).

    Applied at every step, the paper's clamp locks exploration: once the entropy overshoots below its target, alpha can
    never rise to pull it back. ``"above_target"`` holds alpha only while the entropy is at or above the target (then
    alpha's gradient asks for no increase, only Adam's momentum could give one), so alpha may rise as far as it takes
    to bring a collapsed entropy back to the target, never further.

    :param log_ent_coef: log(alpha) after the optimizer step
    :param previous: log(alpha) before it
    :param entropy_gap: Weighted batch mean of ``log pi + target_entropy`` (> 0: entropy below the target)
    :param mode: True (the paper's clamp), ``"above_target"`` or False (no clamp)
    :return: The clamped log(alpha)
    """
    if not mode:
        return log_ent_coef
    clamped = th.minimum(log_ent_coef, previous)
    if mode == "above_target":
        clamped = th.where(entropy_gap > 0, log_ent_coef, clamped)
    return clamped


def update_log_ent_coef(
    log_ent_coef: th.Tensor,
    optimizer: th.optim.Optimizer,
    log_prob: th.Tensor,
    weights: th.Tensor,
    weight_sum: th.Tensor,
    target_entropy: th.Tensor | float,
    mode: bool | str = "above_target",
    average: Callable[[th.Tensor], th.Tensor] | None = None,
) -> th.Tensor:
    """
    One update of the learned entropy coefficient (paper Eq. 12) followed by its clamp (``clamped_log_ent_coef``):
    alpha rises when the entropy is below the target ``target_entropy``, falls when it is above.

    :param log_ent_coef: log(alpha), updated in place
    :param optimizer: Its optimizer
    :param log_prob: Log-probabilities of the actor's actions on the minibatch (their gradients are not used)
    :param weights: Weights of the minibatch's transitions
    :param weight_sum: Their sum (at least 1)
    :param target_entropy: The target entropy ``-beta * |A|``
    :param mode: The clamp: True (the paper's), ``"above_target"`` or False
    :param average: With data-parallel training, the mean over the ranks: of the entropy gap, which is both the
        gradient and what the clamp decides on, so that every rank updates alpha alike
    :return: The loss of the update (detached)
    """
    entropy_gap = ((log_prob.detach() + target_entropy) * weights).sum() / weight_sum
    if average is not None:
        entropy_gap = average(entropy_gap)
    loss = -(log_ent_coef * entropy_gap).sum()
    previous = log_ent_coef.detach().clone()
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    if mode:
        with th.no_grad():
            log_ent_coef.copy_(clamped_log_ent_coef(log_ent_coef, previous, entropy_gap, mode))
    return loss.detach()
