"""
CGAC's twin (n) Q critics: SB3's ``ContinuousCritic`` with the paper code's initialisation, all Q-values at once, and
optionally LayerNorm after each hidden layer and a categorical (histogram) head instead of one scalar per critic.
"""

from collections.abc import Callable

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import ContinuousCritic
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import PyTorchObs
from torch import nn


def output_layer_in_float32(linear: Callable[[th.Tensor], th.Tensor], x: th.Tensor) -> th.Tensor:
    """
    Apply a critic's output layer in float32 even under autocast. Q-values are sums of rewards (hundreds or thousands),
    and bfloat16 keeps 8 bits of mantissa: rounded to bfloat16 they would move in steps larger than the TD errors
    the critic has to fit (a Q of 500 has a resolution of 2). The hidden layers stay in the autocast dtype.

    :param linear: The output layer (called with its input)
    :param x: Its input (possibly in the autocast dtype)
    :return: Its output in float32 (unchanged without autocast)
    """
    if not th.is_autocast_enabled(x.device.type):
        return linear(x)
    with th.autocast(x.device.type, enabled=False):
        return linear(x.float())


# Limits of the categorical critics' support, in symlog space: returns of magnitude up to symexp(10), about 22,000
SYMLOG_LIMIT = 10.0
# The HL-Gauss target's standard deviation, in bin widths (Farebrother et al., 2024, "Stop Regressing")
HL_GAUSS_SIGMA = 0.75


def symlog(x: th.Tensor) -> th.Tensor:
    """``sign(x) * log(1 + |x|)``: compresses large magnitudes, near the identity around 0 (DreamerV3)."""
    return th.sign(x) * th.log1p(x.abs())


def symexp(x: th.Tensor) -> th.Tensor:
    """The inverse of ``symlog``."""
    return th.sign(x) * th.expm1(x.abs())


class HistogramSupport(nn.Module):
    """
    A fixed categorical support for Q-values: ``n_bins`` equal bins over ``[-SYMLOG_LIMIT, SYMLOG_LIMIT]`` in symlog
    space, so that one support covers returns up to about 22,000 in magnitude with no per-task range. A scalar
    target (a Q-GAE(lambda) return, paper Eq. 9-10) becomes a distribution by HL-Gauss: the mass of a Gaussian centred
    on its symlog, of standard deviation 0.75 bin widths, that falls in each bin; the critics are trained by
    cross-entropy to it, and their Q-value is the symexp of the expected bin centre.

    :param n_bins: Number of bins (at least 2)
    """

    edges: th.Tensor
    centers: th.Tensor

    def __init__(self, n_bins: int):
        super().__init__()
        edges = th.linspace(-SYMLOG_LIMIT, SYMLOG_LIMIT, n_bins + 1)
        self.sigma = HL_GAUSS_SIGMA * 2 * SYMLOG_LIMIT / n_bins
        # Not saved: n_bins determines them
        self.register_buffer("edges", edges, persistent=False)
        self.register_buffer("centers", (edges[:-1] + edges[1:]) / 2, persistent=False)

    def expected_value(self, logits: th.Tensor) -> th.Tensor:
        """:return: The Q-values of logits over the bins (last dimension), in float32"""
        return symexp(th.softmax(logits.float(), dim=-1) @ self.centers)

    def target_probabilities(self, returns: th.Tensor) -> th.Tensor:
        """:return: The HL-Gauss distributions of scalar targets over the bins, shape ``(*returns.shape, n_bins)``"""
        mean = symlog(returns).clamp(-SYMLOG_LIMIT, SYMLOG_LIMIT).unsqueeze(-1)
        cdf = th.special.ndtr((self.edges - mean) / self.sigma)
        mass = cdf[..., 1:] - cdf[..., :-1]
        # The Gaussian's tails beyond the support are left out (a target at a limit puts half its mass outside)
        return mass / (cdf[..., -1:] - cdf[..., :1]).clamp_min(1e-6)

    def cross_entropy(self, logits: th.Tensor, returns: th.Tensor) -> th.Tensor:
        """
        :param logits: Logits of each critic, shape ``(n_critics, batch, n_bins)``
        :param returns: Scalar targets, shape ``(batch,)``
        :return: The cross-entropy of each critic and sample, shape ``(n_critics, batch)``
        """
        return -(self.target_probabilities(returns) * th.log_softmax(logits.float(), dim=-1)).sum(dim=-1)


def critic_mlp(
    input_dim: int, output_dim: int, net_arch: list[int], activation_fn: type[nn.Module], layer_norm: bool
) -> nn.Sequential:
    """SB3's ``create_mlp`` with, optionally, a LayerNorm between each hidden linear layer and its activation."""
    layers: list[nn.Module] = []
    for size in net_arch:
        layers += [nn.Linear(input_dim, size), *([nn.LayerNorm(size)] if layer_norm else []), activation_fn()]
        input_dim = size
    layers.append(nn.Linear(input_dim, output_dim))
    return nn.Sequential(*layers)


def xavier_init(module: nn.Module) -> None:
    """Xavier-uniform weights and zero biases for every linear layer (the initialisation of the paper's code)."""
    for layer in module.modules():
        if isinstance(layer, nn.Linear):
            nn.init.xavier_uniform_(layer.weight)
            nn.init.zeros_(layer.bias)


class CGACCritic(ContinuousCritic):
    """
    SB3's twin Q networks (``ContinuousCritic``) with Xavier-uniform initialisation (the paper's code) and
    ``q_values``, the Q-values of every critic as one tensor, whose output layers run in float32 under autocast.

    :param observation_space: Observation space
    :param action_space: Action space
    :param net_arch: Network architecture
    :param features_extractor: Network to extract features
    :param features_dim: Number of features
    :param activation_fn: Activation function
    :param normalize_images: Whether to normalize images or not, dividing by 255.0
    :param n_critics: Number of critic networks to create
    :param share_features_extractor: Whether the features extractor is shared with the actor
    :param use_xavier_init: Whether to use Xavier-uniform weights and zero biases (the paper's code)
    :param layer_norm: Whether to put a LayerNorm between each hidden layer and its activation
    :param n_bins: None: each critic outputs one Q-value, regressed to its targets (paper Eq. 8); a number: each
        outputs logits over a ``HistogramSupport`` of that many bins, trained by cross-entropy
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        net_arch: list[int],
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        activation_fn: type[nn.Module] = nn.ELU,
        normalize_images: bool = True,
        n_critics: int = 2,
        share_features_extractor: bool = False,
        use_xavier_init: bool = True,
        layer_norm: bool = False,
        n_bins: int | None = None,
    ):
        super().__init__(
            observation_space,
            action_space,
            net_arch,
            features_extractor,
            features_dim,
            activation_fn,
            normalize_images,
            n_critics,
            share_features_extractor,
        )
        self.layer_norm = layer_norm
        self.support = None if n_bins is None else HistogramSupport(n_bins)
        if layer_norm or n_bins is not None:
            # SB3's networks rebuilt with the norms and the bins (the default critics keep SB3's, and their seeds)
            input_dim = features_dim + get_action_dim(action_space)
            for idx in range(n_critics):
                network = critic_mlp(input_dim, n_bins or 1, net_arch, activation_fn, layer_norm)
                self.q_networks[idx] = network
                setattr(self, f"qf{idx}", network)
        if use_xavier_init:
            for q_net in self.q_networks:
                xavier_init(q_net)

    def q_outputs(self, obs: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """
        :param obs: Observations, batch size B
        :param actions: Squashed actions, shape (B, action_dim)
        :return: The output of every critic's network, shape (n_critics, B, 1 or n_bins), in float32 under autocast
        """
        with th.set_grad_enabled(th.is_grad_enabled() and not self.share_features_extractor):
            features = self.extract_features(obs, self.features_extractor)
        q_input = th.cat([features, actions], dim=1)
        outputs = []
        for q_net in self.q_networks:
            assert isinstance(q_net, nn.Sequential)
            outputs.append(output_layer_in_float32(q_net[-1], q_net[:-1](q_input)))
        return th.stack(outputs)

    def q_values_from_outputs(self, outputs: th.Tensor) -> th.Tensor:
        """:return: The Q-values of ``q_outputs``, shape (n_critics, B)"""
        return outputs.squeeze(-1) if self.support is None else self.support.expected_value(outputs)

    def q_values(self, obs: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """
        :param obs: Observations, batch size B
        :param actions: Squashed actions, shape (B, action_dim)
        :return: The Q-values of every critic, shape (n_critics, B)
        """
        return self.q_values_from_outputs(self.q_outputs(obs, actions))

    def set_q_requires_grad(self, requires_grad: bool) -> None:
        """
        Switch the gradients of the Q networks on or off (not those of a features extractor shared with the actor).

        :param requires_grad: Whether the Q networks' parameters require gradients
        """
        for q_net in self.q_networks:
            q_net.requires_grad_(requires_grad)
