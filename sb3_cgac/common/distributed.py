"""
Data-parallel CGAC over ``torch.distributed`` (launched with ``torchrun``): every rank steps its own envs into its own
window, and every update averages the gradients of all ranks, so that the ranks hold identical parameters.

    torchrun --nproc-per-node 2 examples/distributed.py --env HalfCheetah-v5

``CGAC`` detects an initialised process group by itself; :func:`init_from_env` joins the one ``torchrun`` describes.
"""

import datetime
import os
import sys
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch as th
import torch.distributed as dist
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.vec_env import VecNormalize

# Rank r's seed is the model's seed + r * RANK_SEED_STRIDE: each rank's envs (seed + i) and minibatches differ
RANK_SEED_STRIDE = 1_000_000
# Up to this many gloo ranks, a sum over the ranks is an all-gather and a local sum in rank order (the same on every
# rank), which on gloo is faster than its all-reduce for gradient-sized tensors (docs/performance.md, "Data-parallel
# training on one CPU"). Beyond it the gathered bytes grow with the ranks: all-reduce. NCCL always all-reduces.
GATHER_SUM_MAX_RANKS = 4


def world() -> tuple[int, int]:
    """The rank of this process and the number of ranks: (0, 1) without an initialised process group."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def init_from_env(backend: str | None = None, timeout_s: float = 600.0) -> tuple[int, int]:
    """
    Join the process group that ``torchrun`` describes in the environment (``RANK``, ``WORLD_SIZE``,
    ``MASTER_ADDR``, ``MASTER_PORT``); a plain ``python`` run (no ``WORLD_SIZE``, or 1) stays a single process.

    :param backend: ``"gloo"`` (CPU) or ``"nccl"`` (CUDA); None: NCCL when CUDA is available, else gloo
    :param timeout_s: How long a collective waits for the other ranks before it fails, so that a rank that died
        ends the run with an error instead of a hang
    :return: (rank, world size)
    """
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return world()
    if not dist.is_initialized():
        backend = backend or ("nccl" if th.cuda.is_available() else "gloo")
        if backend == "nccl":
            th.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
        dist.init_process_group(backend, timeout=datetime.timedelta(seconds=timeout_s))
    return world()


def leave() -> None:
    """
    End a rank's process after data-parallel training: wait for every rank, destroy the process group and exit
    without the interpreter's finalisation, during which gloo's threads can abort the process ("terminate called
    without an active exception"). Without a process group: nothing.
    """
    if not (dist.is_available() and dist.is_initialized()):
        return
    dist.barrier()
    dist.destroy_process_group()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


class DataParallel:
    """
    The collectives of data-parallel CGAC, over the default process group.

    :param device: Device of the model's tensors (NCCL reduces CUDA tensors, gloo CPU ones)
    """

    def __init__(self, device: th.device):
        self.rank, self.world_size = world()
        self.device = device
        self._gather_sum = dist.get_backend() == "gloo" and self.world_size <= GATHER_SUM_MAX_RANKS
        self._vec_normalize_sync: VecNormalizeSync | None = None

    def start(self, settings: Mapping[str, int], tensors: Sequence[th.Tensor], vec_normalize: VecNormalize | None) -> None:
        """
        Start data-parallel training: check that every rank has the same ``settings`` (env counts, batch sizes: the
        updates of all ranks run in step), give every rank rank 0's ``tensors`` (parameters) and VecNormalize statistics.
        """
        for name, value in settings.items():
            self.check_same(name, value)
        self.broadcast_tensors(tensors)
        self.sync_vec_normalize(vec_normalize)

    def sync_vec_normalize(self, vec_normalize: VecNormalize | None) -> None:
        """
        Merge the ``VecNormalize`` statistics of every rank (``VecNormalizeSync``; the first call gives every rank
        rank 0's); no-op without a ``VecNormalize`` or when it does not update its statistics.
        """
        if vec_normalize is None or not vec_normalize.training:
            return
        if self._vec_normalize_sync is None or self._vec_normalize_sync.vec_normalize is not vec_normalize:
            self._vec_normalize_sync = VecNormalizeSync(self, vec_normalize)
        self._vec_normalize_sync()

    def average_gradients(self, parameters: Sequence[th.Tensor]) -> None:
        """Replace each parameter's gradient by its mean over the ranks (one all-reduce of the flattened gradients)."""
        grads = [param.grad for param in parameters if param.grad is not None]
        if not grads:
            return
        flat = self.sum(th.cat([grad.reshape(-1) for grad in grads]))
        flat /= self.world_size
        offset = 0
        for grad in grads:
            grad.copy_(flat[offset : offset + grad.numel()].view_as(grad))
            offset += grad.numel()

    def gather(self, tensor: th.Tensor) -> th.Tensor:
        """Every rank's ``tensor``, concatenated along the last dimension in rank order."""
        parts = [th.empty_like(tensor) for _ in range(self.world_size)]
        dist.all_gather(parts, tensor.contiguous())
        return th.cat(parts, dim=-1)

    def sum(self, tensor: th.Tensor) -> th.Tensor:
        """The sum of ``tensor`` over the ranks (a new tensor, bit-identical on every rank)."""
        if self._gather_sum:
            parts = [th.empty_like(tensor) for _ in range(self.world_size)]
            dist.all_gather(parts, tensor.contiguous())
            total = parts[0]
            for part in parts[1:]:
                total += part
            return total
        total = tensor.clone()
        dist.all_reduce(total)
        return total

    def max(self, tensor: th.Tensor) -> th.Tensor:
        """The elementwise maximum of ``tensor`` over the ranks (a new tensor)."""
        total = tensor.clone()
        dist.all_reduce(total, op=dist.ReduceOp.MAX)
        return total

    def mean(self, tensor: th.Tensor) -> th.Tensor:
        """The mean of ``tensor`` over the ranks (a new tensor)."""
        return self.sum(tensor) / self.world_size

    def mean_float(self, value: float) -> float:
        return float(self.mean(th.tensor(value, dtype=th.float64, device=self.device)).item())

    def all_agree(self, flag: bool) -> bool:
        """True only if ``flag`` is True on every rank (e.g. no callback asked to stop)."""
        value = th.tensor(int(flag), device=self.device)
        dist.all_reduce(value, op=dist.ReduceOp.MIN)
        return bool(value.item())

    def check_same(self, name: str, value: int) -> None:
        """Fail with a clear error unless every rank has the same ``value`` (env counts, batch sizes...)."""
        values = [th.zeros((), dtype=th.int64, device=self.device) for _ in range(self.world_size)]
        dist.all_gather(values, th.tensor(value, dtype=th.int64, device=self.device))
        found = [int(found.item()) for found in values]
        if len(set(found)) > 1:
            raise ValueError(
                f"CGAC with torch.distributed: every rank needs the same {name}, got {found} (rank by rank); the "
                "updates of all ranks run in step."
            )

    def broadcast_tensors(self, tensors: Sequence[th.Tensor]) -> None:
        """Copy rank 0's values of ``tensors`` (parameters, buffers) to every rank, in place."""
        with th.no_grad():
            for tensor in tensors:
                dist.broadcast(tensor.data, src=0)


def start_data_parallel(model: Any) -> DataParallel:
    """
    Start data-parallel training of a CGAC model on every rank (its ``learn()`` calls this under torchrun): the ranks
    must agree on the settings that keep their updates in step, and start from rank 0's parameters, entropy
    coefficient and VecNormalize statistics.
    """
    if model.cuda_graphs:
        raise ValueError("CGAC: cuda_graphs=True does not run with torch.distributed yet; pass cuda_graphs=False.")
    parallel = DataParallel(model.device)
    settings = {name: getattr(model, name) for name in ("n_envs", "n_steps", "batch_size", "critic_updates_per_step")}
    tensors = [*model.policy.state_dict().values(), *([model.log_ent_coef] if model.log_ent_coef is not None else [])]
    parallel.start(settings, tensors, model.get_vec_normalize_env())
    return parallel


class VecNormalizeSync:
    """
    Keeps the ``VecNormalize`` statistics of every rank equal: each call merges the observations (and returns)
    that every rank has seen since the previous call into statistics common to all ranks, as if one ``VecNormalize``
    had seen them all. Between calls each rank's statistics move with its own observations only.

    :param parallel: The collectives
    :param vec_normalize: This rank's ``VecNormalize``
    """

    def __init__(self, parallel: DataParallel, vec_normalize: VecNormalize):
        self.parallel = parallel
        self.vec_normalize = vec_normalize
        self._common: list[tuple[float, np.ndarray, np.ndarray]] | None = None

    def _statistics(self) -> list[RunningMeanStd]:
        obs_rms = self.vec_normalize.obs_rms
        found = list(obs_rms.values()) if isinstance(obs_rms, dict) else [obs_rms]
        return [*found, self.vec_normalize.ret_rms]

    def __call__(self) -> None:
        statistics = self._statistics()
        if self._common is None:  # the first call: rank 0's statistics are the common start
            for rms in statistics:
                tensor = th.as_tensor(
                    np.concatenate([[rms.count], rms.mean.ravel(), rms.var.ravel()]), device=self.parallel.device
                )
                dist.broadcast(tensor, src=0)
                values = tensor.cpu().numpy()
                size = rms.mean.size
                rms.count, rms.mean, rms.var = (
                    float(values[0]),
                    values[1 : 1 + size].reshape(rms.mean.shape),
                    values[1 + size :].reshape(rms.var.shape),
                )
        else:
            for rms, (count, mean, var) in zip(statistics, self._common, strict=True):
                # This rank's new data since the common statistics: count, sum and sum of squares
                new_count = rms.count - count
                new_sum = rms.mean * rms.count - mean * count
                new_squares = (rms.var + rms.mean**2) * rms.count - (var + mean**2) * count
                local = np.concatenate([[new_count], new_sum.ravel(), new_squares.ravel()])
                total = self.parallel.sum(th.as_tensor(local, dtype=th.float64, device=self.parallel.device)).cpu().numpy()
                size = mean.size
                merged_count = count + total[0]
                merged_mean = (mean * count + total[1 : 1 + size].reshape(mean.shape)) / merged_count
                squares = (var + mean**2) * count + total[1 + size :].reshape(var.shape)
                rms.count, rms.mean, rms.var = (
                    merged_count,
                    merged_mean,
                    np.maximum(squares / merged_count - merged_mean**2, 0.0),
                )
        self._common = [(float(rms.count), rms.mean.copy(), rms.var.copy()) for rms in statistics]
