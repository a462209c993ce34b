"""CGAC's twin (n) Q critics: SB3's ``ContinuousCritic``, optionally with LayerNorm, optionally stacked into one network."""

from collections.abc import Callable
from functools import partial
from typing import Any

import torch as th
import torch.nn.functional as F
from gymnasium import spaces
from stable_baselines3.common.policies import ContinuousCritic
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import PyTorchObs
from torch import nn


def output_layer_in_float32(linear: Callable[[th.Tensor], th.Tensor], x: th.Tensor, enabled: bool = True) -> th.Tensor:
    """
    Apply a critic's output layer in float32 even under autocast. Q-values are sums of rewards (hundreds or thousands),
    and bfloat16 keeps 8 bits of mantissa: rounded to bfloat16 they would move in steps larger than the TD errors
    the critic has to fit (a Q of 500 has a resolution of 2). The hidden layers stay in the autocast dtype.

    :param linear: The output layer (called with its input)
    :param x: Its input (possibly in the autocast dtype)
    :param enabled: False applies the layer as it is (in the autocast dtype under autocast: Q-values in bfloat16)
    :return: Its output in float32 (unchanged without autocast or when not enabled)
    """
    if not enabled or not th.is_autocast_enabled(x.device.type):
        return linear(x)
    with th.autocast(x.device.type, enabled=False):
        return linear(x.float())


def batched_linear(x: th.Tensor, weight: th.Tensor, bias: th.Tensor) -> th.Tensor:
    """
    :param x: Inputs of every network, shape (n, batch, in)
    :param weight: Stacked weights, shape (n, out, in)
    :param bias: Stacked biases, shape (n, 1, out)
    :return: Outputs, shape (n, batch, out)
    """
    return th.baddbmm(bias, x, weight.transpose(1, 2))


def xavier_init(module: nn.Module) -> None:
    """Xavier-uniform weights and zero biases for every linear layer (the initialisation of the paper's code)."""
    for layer in module.modules():
        if isinstance(layer, nn.Linear):
            nn.init.xavier_uniform_(layer.weight)
            nn.init.zeros_(layer.bias)


class StackedMlp(nn.Module):
    """
    ``n`` MLPs of the same shape evaluated as one: each layer's weights are stacked along a leading dim, so a layer is
    one batched matmul for all networks instead of one matmul per network. Built from ``nn.Sequential`` networks of
    ``Linear [LayerNorm] activation ... Linear`` layers, whose values it takes.

    :param networks: The networks to stack (same layer sizes)
    :param activation_fn: Their activation function (applied element-wise)
    :param float32_output: Whether the output layer runs in float32 under autocast (``output_layer_in_float32``)
    """

    def __init__(self, networks: list[nn.Sequential], activation_fn: type[nn.Module], float32_output: bool = True):
        super().__init__()
        self.n_networks = len(networks)
        self.float32_output = float32_output
        linear = [[layer for layer in net if isinstance(layer, nn.Linear)] for net in networks]
        norms = [[layer for layer in net if isinstance(layer, nn.LayerNorm)] for net in networks]

        def stack(layers: list[nn.Module], name: str, bias_like: bool) -> nn.Parameter:
            values = th.stack([getattr(layer, name).detach() for layer in layers])
            return nn.Parameter(values.unsqueeze(1) if bias_like else values)

        # weights[l]: (n, out, in), biases[l]: (n, 1, out), as nn.Linear's (out, in) weights
        self.weights = nn.ParameterList(stack(list(layers), "weight", False) for layers in zip(*linear, strict=True))
        self.biases = nn.ParameterList(stack(list(layers), "bias", True) for layers in zip(*linear, strict=True))
        self.norm_weights = nn.ParameterList(stack(list(layers), "weight", True) for layers in zip(*norms, strict=True))
        self.norm_biases = nn.ParameterList(stack(list(layers), "bias", True) for layers in zip(*norms, strict=True))
        self.activation = activation_fn()

    def forward(self, x: th.Tensor) -> th.Tensor:
        """
        :param x: The input shared by all networks, shape (batch, in)
        :return: The outputs of every network, shape (n_networks, batch, out)
        """
        # The first layer is one matmul with the networks' weights side by side
        n, width, in_dim = self.weights[0].shape
        h = F.linear(x, self.weights[0].reshape(n * width, in_dim), self.biases[0].reshape(n * width))
        h = h.view(x.shape[0], n, width).transpose(0, 1)
        last = len(self.weights) - 1
        for layer in range(1, len(self.weights)):
            if len(self.norm_weights) > 0:
                h = F.layer_norm(h, (h.shape[-1],)) * self.norm_weights[layer - 1] + self.norm_biases[layer - 1]
            h = self.activation(h)
            if layer == last:
                output_layer = partial(batched_linear, weight=self.weights[layer], bias=self.biases[layer])
                return output_layer_in_float32(output_layer, h, self.float32_output)
            h = batched_linear(h, self.weights[layer], self.biases[layer])
        return h


class CGACCritic(ContinuousCritic):
    """
    SB3's twin Q networks (``ContinuousCritic``), optionally with LayerNorm after every hidden linear layer
    (before the activation), a stabiliser of critic-gradient methods (FastTD3, BRO, SimBa, PQN), and optionally
    stacked: all critics evaluated as one batched computation (``StackedMlp``). A stacked critic loads the state dicts
    of separate critics (and the other way round), so models saved either way load into both.

    :param observation_space: Observation space
    :param action_space: Action space
    :param net_arch: Network architecture
    :param features_extractor: Network to extract features
    :param features_dim: Number of features
    :param activation_fn: Activation function
    :param normalize_images: Whether to normalize images or not, dividing by 255.0
    :param n_critics: Number of critic networks to create
    :param share_features_extractor: Whether the features extractor is shared with the actor
    :param layer_norm: Whether to put LayerNorm after every hidden linear layer
    :param use_xavier_init: Whether to use Xavier-uniform weights and zero biases (the paper's code)
    :param stacked: Whether to evaluate the critics as one stacked network
    :param float32_output: Whether the output layers run in float32 under bfloat16 autocast (False: the Q-values are
        computed and rounded in bfloat16, as the hidden layers are)
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
        layer_norm: bool = False,
        use_xavier_init: bool = True,
        stacked: bool = False,
        float32_output: bool = True,
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
        self.float32_output = float32_output
        for idx, q_net in enumerate(self.q_networks):
            assert isinstance(q_net, nn.Sequential)
            if layer_norm:
                layers: list[nn.Module] = []
                for layer in q_net:
                    layers.append(layer)
                    if isinstance(layer, nn.Linear) and layer is not q_net[-1]:
                        layers.append(nn.LayerNorm(layer.out_features))
                self.q_networks[idx] = q_net = nn.Sequential(*layers)
                self.add_module(f"qf{idx}", q_net)
            if use_xavier_init:
                xavier_init(q_net)
        # Which parameter of separate critics (index in their nn.Sequential) is which of a stacked critic, for state dicts
        layers = list(self.q_networks[0].children())
        linear = [idx for idx, layer in enumerate(layers) if isinstance(layer, nn.Linear)]
        norms = [idx for idx, layer in enumerate(layers) if isinstance(layer, nn.LayerNorm)]
        self._stacked_names: list[tuple[str, str, bool]] = [
            *((f"weights.{k}", f"{idx}.weight", False) for k, idx in enumerate(linear)),
            *((f"biases.{k}", f"{idx}.bias", True) for k, idx in enumerate(linear)),
            *((f"norm_weights.{k}", f"{idx}.weight", True) for k, idx in enumerate(norms)),
            *((f"norm_biases.{k}", f"{idx}.bias", True) for k, idx in enumerate(norms)),
        ]
        self.q_stack: StackedMlp | None = None
        if stacked:
            self.q_stack = StackedMlp(self.q_networks, activation_fn, float32_output)  # type: ignore[arg-type]
            for idx in range(n_critics):
                delattr(self, f"qf{idx}")
            self.q_networks = []
        self.register_load_state_dict_pre_hook(self._convert_state_dict)

    def forward(self, obs: PyTorchObs, actions: th.Tensor) -> tuple[th.Tensor, ...]:
        if self.q_stack is None:
            return super().forward(obs, actions)  # type: ignore[arg-type]
        return tuple(self.q_values(obs, actions).unsqueeze(-1).unbind(0))

    def q1_forward(self, obs: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        if self.q_stack is None:
            return super().q1_forward(obs, actions)  # type: ignore[arg-type]
        with th.no_grad():
            return self.q_values(obs, actions)[0].unsqueeze(-1)

    def q_values(self, obs: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """
        :param obs: Observations, batch size B
        :param actions: Squashed actions, shape (B, action_dim)
        :return: The Q-values of every critic, shape (n_critics, B)
        """
        with th.set_grad_enabled(th.is_grad_enabled() and not self.share_features_extractor):
            features = self.extract_features(obs, self.features_extractor)
        q_input = th.cat([features, actions], dim=1)
        if self.q_stack is not None:
            return self.q_stack(q_input).squeeze(-1)
        q_values = []
        for q_net in self.q_networks:
            assert isinstance(q_net, nn.Sequential)
            q_values.append(output_layer_in_float32(q_net[-1], q_net[:-1](q_input), self.float32_output).squeeze(-1))
        return th.stack(q_values)

    def set_q_requires_grad(self, requires_grad: bool) -> None:
        """
        Switch the gradients of the Q networks on or off (not those of a features extractor shared with the actor).

        :param requires_grad: Whether the Q networks' parameters require gradients
        """
        for q_net in self.q_networks if self.q_stack is None else [self.q_stack]:
            q_net.requires_grad_(requires_grad)

    def _convert_state_dict(self, module: nn.Module, state_dict: dict[str, Any], prefix: str, *args: Any) -> None:
        # Models saved with separate critics load into stacked ones, and the other way round. Stacked names:
        # (name in the stack, name in each nn.Sequential, whether the stack has a middle dim of 1 there)
        for stacked_name, separate_name, middle_dim in self._stacked_names:
            stacked_key, separate_keys = (
                f"{prefix}q_stack.{stacked_name}",
                [f"{prefix}qf{i}.{separate_name}" for i in range(self.n_critics)],
            )
            if self.q_stack is not None and separate_keys[0] in state_dict:
                stacked = th.stack([state_dict.pop(key) for key in separate_keys])
                state_dict[stacked_key] = stacked.unsqueeze(1) if middle_dim else stacked
            elif self.q_stack is None and stacked_key in state_dict:
                stacked = state_dict.pop(stacked_key)
                for i, key in enumerate(separate_keys):
                    state_dict[key] = stacked[i, 0] if middle_dim else stacked[i]
