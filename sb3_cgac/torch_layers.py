"""
Layers of CGAC's policy that act on observations: running normalisation inside the policy (of a Box observation, or of
each Box entry of a Dict observation), and features extractors that read only some keys of a Dict observation (an
actor on what the robot senses, critics on privileged simulator state too).
"""

from collections.abc import Callable

import torch as th
from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import PyTorchObs
from torch import nn

# The authors' code clips normalised observations at +-5
OBS_CLIP = 5.0
# A sum over the ranks of data-parallel training
AllReduce = Callable[[th.Tensor], th.Tensor]


class RunningObsNormalizer(nn.Module):
    """
    Running mean and variance of the observations (merged batch by batch, as SB3's ``RunningMeanStd``), applied as
    ``clip((obs - mean) / sqrt(var + eps), -clip, +clip)``. The statistics are buffers: they are saved with the
    policy and loaded with it, and Polyak updates (which average parameters) leave them alone.

    :param shape: Shape of one observation
    :param clip: Bound on the normalised values (5 in the authors' code)
    :param epsilon: Added to the variance, and the initial count
    """

    mean: th.Tensor
    var: th.Tensor
    count: th.Tensor

    def __init__(self, shape: tuple[int, ...], clip: float = OBS_CLIP, epsilon: float = 1e-8):
        super().__init__()
        self.clip = clip
        self.epsilon = epsilon
        self.register_buffer("mean", th.zeros(shape))
        self.register_buffer("var", th.ones(shape))
        self.register_buffer("count", th.tensor(1e-4))

    @th.no_grad()
    def update(self, obs: th.Tensor, valid: th.Tensor | None = None, all_reduce: AllReduce | None = None) -> None:
        """
        Merge a batch of observations into the statistics, on their device (no host sync).

        :param obs: Observations, shape ``(batch, *shape)``
        :param valid: Which rows to merge (boolean, shape (batch,)); None: all
        :param all_reduce: With data-parallel training, the sum over the ranks (``DataParallel.sum``): the batch is
            then the observations of every rank, and every rank merges the same statistics
        """
        obs = obs.float()
        weights = th.ones(len(obs), device=obs.device) if valid is None else valid.to(obs.device, th.float32)
        weights = weights.reshape(-1, *([1] * (obs.dim() - 1)))
        if all_reduce is None:
            batch_count = weights.sum()
            batch_mean = (obs * weights).sum(dim=0) / batch_count.clamp_min(1.0)
            batch_var = ((obs - batch_mean) ** 2 * weights).sum(dim=0) / batch_count.clamp_min(1.0)
        else:
            # Count, sum and sum of squares of every rank's rows, in float64 for the variance's cancellation
            rows = (obs.double() * weights).reshape(obs.shape[0], -1)
            count = weights.double().sum().reshape(1)
            sums = all_reduce(th.cat([count, rows.sum(dim=0), (rows**2).sum(dim=0)]))
            size = rows.shape[1]
            batch_count = sums[0].float()
            mean64 = sums[1 : 1 + size] / sums[0].clamp_min(1.0)
            batch_mean = mean64.float().view(self.mean.shape)
            batch_var = (sums[1 + size :] / sums[0].clamp_min(1.0) - mean64**2).clamp_min(0.0).float().view(self.mean.shape)
        # A batch without a valid row leaves the statistics as they are (batch_count 0)
        delta = batch_mean - self.mean
        total = self.count + batch_count
        self.var.copy_((self.var * self.count + batch_var * batch_count + delta**2 * self.count * batch_count / total) / total)
        self.mean.add_(delta * batch_count / total)
        self.count.copy_(total)

    def forward(self, obs: th.Tensor) -> th.Tensor:
        return ((obs - self.mean) / th.sqrt(self.var + self.epsilon)).clamp(-self.clip, self.clip)


class DictObsNormalizer(nn.Module):
    """
    A ``RunningObsNormalizer`` for each Box entry of a Dict observation space; the other entries pass unchanged, and
    so do keys absent from a batch (``predict()`` with only the actor's keys).

    :param observation_space: The Dict observation space
    """

    def __init__(self, observation_space: spaces.Dict):
        super().__init__()
        self.normalizers = nn.ModuleDict(
            {
                key: RunningObsNormalizer(space.shape)
                for key, space in observation_space.spaces.items()
                if isinstance(space, spaces.Box)
            }
        )

    @th.no_grad()
    def update(self, obs: dict[str, th.Tensor], valid: th.Tensor | None = None, all_reduce: AllReduce | None = None) -> None:
        for key, normalizer in self.normalizers.items():
            assert isinstance(normalizer, RunningObsNormalizer)
            normalizer.update(obs[key], valid, all_reduce)

    def forward(self, obs: dict[str, th.Tensor]) -> dict[str, th.Tensor]:
        return {key: self.normalizers[key](value) if key in self.normalizers else value for key, value in obs.items()}


ObsNormalizer = RunningObsNormalizer | DictObsNormalizer


class NormalizedFeaturesExtractor(BaseFeaturesExtractor):
    """
    A features extractor preceded by observation normalisation. The policy shares one normalizer between all its
    networks (actor, critics and their averaged copies), so that they all see the same inputs.

    :param observation_space: Observation space
    :param features_extractor: The features extractor that receives the normalised observations
    :param normalizer: The shared running normalizer
    """

    def __init__(self, observation_space: spaces.Space, features_extractor: BaseFeaturesExtractor, normalizer: ObsNormalizer):
        super().__init__(observation_space, features_extractor.features_dim)
        self.extractor = features_extractor
        self.normalizer = normalizer

    def forward(self, observations: PyTorchObs) -> th.Tensor:
        return self.extractor(self.normalizer(observations))  # type: ignore[arg-type]


class DictKeysExtractor(BaseFeaturesExtractor):
    """
    A features extractor of some keys of a Dict observation: ``extractor_class`` built on the sub-space of ``keys``;
    the other keys are ignored (and may be absent).

    :param observation_space: The whole Dict observation space
    :param keys: The keys to read
    :param extractor_class: The features extractor of those keys (e.g. SB3's ``CombinedExtractor``)
    :param extractor_kwargs: Its keyword arguments
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        keys: list[str],
        extractor_class: type[BaseFeaturesExtractor],
        extractor_kwargs: dict | None = None,
    ):
        extractor = extractor_class(spaces.Dict({key: observation_space[key] for key in keys}), **(extractor_kwargs or {}))
        super().__init__(observation_space, extractor.features_dim)
        self.keys = list(keys)
        self.extractor = extractor

    def forward(self, observations: dict[str, th.Tensor]) -> th.Tensor:  # type: ignore[override]
        return self.extractor({key: observations[key] for key in self.keys})
