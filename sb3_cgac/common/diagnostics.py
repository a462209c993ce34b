"""What the updates report: gradient norms, an iteration's statistics read from the device at once, finiteness."""

import torch as th


def total_grad_norm(parameters: list[th.Tensor]) -> th.Tensor:
    """The norm of all gradients together, as ``torch.nn.utils.get_total_norm`` (torch >= 2.6 only) computes it."""
    grads = [param.grad for param in parameters if param.grad is not None]
    return th.linalg.vector_norm(th.stack(th._foreach_norm(grads)))


def read_statistics(scalars: dict[str, th.Tensor], updates: list[dict[str, th.Tensor]]) -> dict[str, float]:
    """
    Read an iteration's statistics from the device in one transfer (no host sync inside the update loop).

    :param scalars: One-element tensors by name
    :param updates: The statistics of each update, by name (the updates of one kind share their names)
    :return: The scalars, and the mean of each statistic over the updates that returned it, by name
    """
    collected: dict[str, list[th.Tensor]] = {name: [value] for name, value in scalars.items()}
    for statistics in updates:
        for name, value in statistics.items():
            collected.setdefault(name, []).append(value)
    means = [th.stack([value.reshape(()).float() for value in values]).mean() for values in collected.values()]
    return dict(zip(collected, th.stack(means).tolist(), strict=True))


def check_finite_parameters(finite: bool, n_updates: int) -> None:
    """Stop training with the likely causes once a parameter became NaN/Inf (it cannot recover)."""
    if not finite:
        raise RuntimeError(
            f"CGAC: network parameters became NaN/Inf after {n_updates} critic updates; training cannot go on. "
            "Common causes: exploding rewards or observations (wrap the env in VecNormalize), a learning rate "
            "too high, or gradient clipping turned off (max_grad_norm)."
        )
