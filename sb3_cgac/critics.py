"""CGAC's twin (n) Q critics: SB3's ``ContinuousCritic`` with the paper code's initialisation, all Q-values at once."""

from collections.abc import Callable

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import ContinuousCritic
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
        if use_xavier_init:
            for q_net in self.q_networks:
                xavier_init(q_net)

    def q_values(self, obs: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """
        :param obs: Observations, batch size B
        :param actions: Squashed actions, shape (B, action_dim)
        :return: The Q-values of every critic, shape (n_critics, B)
        """
        with th.set_grad_enabled(th.is_grad_enabled() and not self.share_features_extractor):
            features = self.extract_features(obs, self.features_extractor)
        q_input = th.cat([features, actions], dim=1)
        q_values = []
        for q_net in self.q_networks:
            assert isinstance(q_net, nn.Sequential)
            q_values.append(output_layer_in_float32(q_net[-1], q_net[:-1](q_input)).squeeze(-1))
        return th.stack(q_values)

    def set_q_requires_grad(self, requires_grad: bool) -> None:
        """
        Switch the gradients of the Q networks on or off (not those of a features extractor shared with the actor).

        :param requires_grad: Whether the Q networks' parameters require gradients
        """
        for q_net in self.q_networks:
            q_net.requires_grad_(requires_grad)
