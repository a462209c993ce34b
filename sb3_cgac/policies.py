"""Policies for CGAC: a tanh-squashed Gaussian actor, twin Q critics and their Polyak-averaged copies."""

import math
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.distributions import SquashedDiagGaussianDistribution
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.torch_layers import (
    BaseFeaturesExtractor,
    CombinedExtractor,
    FlattenExtractor,
    create_mlp,
    get_actor_critic_arch,
)
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_cgac.critics import CGACCritic, xavier_init
from sb3_cgac.torch_layers import (
    AllReduce,
    DictKeysExtractor,
    DictObsNormalizer,
    NormalizedFeaturesExtractor,
    ObsNormalizer,
    RunningObsNormalizer,
)

# Same caps on the log standard deviation as SB3's SAC
LOG_STD_MAX = 2
LOG_STD_MIN = -20
LOG_SQRT_2PI = math.log(math.sqrt(2 * math.pi))  # as torch.distributions.Normal computes it
TANH_EPSILON = 1e-6  # SB3's SquashedDiagGaussianDistribution's epsilon in the log-probability of tanh(x)
# Hidden layers of actor and critics when policy_kwargs name no net_arch (the paper's Table 1)
DEFAULT_NET_ARCH = [256, 256]


class Actor(BasePolicy):
    """
    Tanh-squashed diagonal Gaussian actor (paper Sec. 4.1: "the policy network outputs the mean and
    standard deviation to parameterize a gaussian distribution").

    :param observation_space: Observation space
    :param action_space: Action space
    :param net_arch: Network architecture (hidden layer sizes)
    :param features_extractor: Network to extract features
    :param features_dim: Number of features
    :param activation_fn: Activation function
    :param log_std_init: Initial value of the log standard deviation
    :param use_xavier_init: Whether to use Xavier-uniform weights and zero biases (the paper's code)
    :param mean_init_scale: Factor on the initial weights and bias of the layer that outputs the Gaussian's mean
    :param normalize_images: Whether to normalize images or not, dividing by 255.0
    """

    action_space: spaces.Box

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        net_arch: list[int],
        features_extractor: nn.Module,
        features_dim: int,
        activation_fn: type[nn.Module] = nn.ELU,
        log_std_init: float = -1.0,
        use_xavier_init: bool = True,
        mean_init_scale: float = 1.0,
        normalize_images: bool = True,
    ):
        super().__init__(
            observation_space,
            action_space,
            features_extractor=features_extractor,
            normalize_images=normalize_images,
            squash_output=True,
        )
        self.net_arch = net_arch
        self.features_dim = features_dim
        self.activation_fn = activation_fn
        self.log_std_init = log_std_init
        self.use_xavier_init = use_xavier_init
        self.mean_init_scale = mean_init_scale

        action_dim = get_action_dim(self.action_space)
        self.latent_pi = nn.Sequential(*create_mlp(features_dim, -1, net_arch, activation_fn))
        last_layer_dim = net_arch[-1] if len(net_arch) > 0 else features_dim
        self.mu = nn.Linear(last_layer_dim, action_dim)
        # A learnable state-independent log standard deviation (the paper's code)
        self.log_std = nn.Parameter(th.full((action_dim,), float(log_std_init)))
        if use_xavier_init:
            xavier_init(self)
        if mean_init_scale != 1.0:
            # A small factor starts from near-zero mean actions whatever the observation (SB3's PPO scales its action
            # head by 0.01 for the same reason): the untrained deterministic policy is then the env's "do nothing".
            with th.no_grad():
                self.mu.weight.mul_(mean_init_scale)
                self.mu.bias.mul_(mean_init_scale)
        self.action_dist = SquashedDiagGaussianDistribution(action_dim)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            dict(
                net_arch=self.net_arch,
                features_dim=self.features_dim,
                activation_fn=self.activation_fn,
                log_std_init=self.log_std_init,
                use_xavier_init=self.use_xavier_init,
                mean_init_scale=self.mean_init_scale,
                features_extractor=self.features_extractor,
            )
        )
        return data

    def get_action_dist_params(self, obs: PyTorchObs) -> tuple[th.Tensor, th.Tensor]:
        """
        :param obs: Observations
        :return: Mean and log standard deviation of the Gaussian before the tanh squashing
        """
        latent_pi = self.latent_pi(self.extract_features(obs, self.features_extractor))
        mean_actions = self.mu(latent_pi)
        return mean_actions, th.clamp(self.log_std, LOG_STD_MIN, LOG_STD_MAX)

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        mean_actions, log_std = self.get_action_dist_params(obs)
        return self.action_dist.actions_from_params(mean_actions, log_std, deterministic=deterministic)

    def action_log_prob(self, obs: PyTorchObs) -> tuple[th.Tensor, th.Tensor]:
        """
        Reparameterised actions and their log-likelihood, for the actor loss (paper Eq. 7).

        :param obs: Observations
        :return: Squashed actions and their log probability
        """
        mean_actions, log_std = self.get_action_dist_params(obs)
        # The arithmetic of SB3's SquashedDiagGaussianDistribution.log_prob_from_params, op for op, without
        # torch.distributions: its argument checks read tensors on the host, a device sync in every update on a GPU,
        # which a CUDA graph cannot hold
        std = th.ones_like(mean_actions) * log_std.exp()
        noise = th.empty(std.shape, dtype=mean_actions.dtype, device=mean_actions.device).normal_()
        gaussian_actions = mean_actions + noise * std
        actions = th.tanh(gaussian_actions)
        gaussian_log_prob = -((gaussian_actions - mean_actions) ** 2) / (2 * std**2) - std.log() - LOG_SQRT_2PI
        log_prob = gaussian_log_prob.sum(dim=1) - th.sum(th.log(1 - actions**2 + TANH_EPSILON), dim=1)
        return actions, log_prob

    def sample(self, obs: PyTorchObs, n_samples: int) -> th.Tensor:
        """
        Draw several independent squashed actions per observation from one forward pass.
        CGAC needs two per step: the action to take and the "next action" of the previous transition.

        :param obs: Observations, batch size B
        :param n_samples: Number of draws per observation
        :return: Actions of shape (n_samples, B, action_dim)
        """
        mean_actions, log_std = self.get_action_dist_params(obs)
        noise = th.randn((n_samples, *mean_actions.shape), device=mean_actions.device, dtype=mean_actions.dtype)
        return th.tanh(mean_actions + log_std.exp() * noise)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self(observation, deterministic)


def check_policy_arguments(
    action_space: spaces.Space, mean_init_scale: float, n_bins: int | None, n_critics: int, actor_q_reduction: str
) -> None:
    """Check the arguments of ``CGACPolicy`` that build its networks (see there); each error names the fix."""
    if not isinstance(action_space, spaces.Box):
        raise ValueError(
            f"CGACPolicy needs a continuous (gymnasium.spaces.Box) action space, got {action_space}: CGAC "
            "follows the gradient of Q through the action (paper Eq. 7)."
        )
    if not (math.isfinite(mean_init_scale) and mean_init_scale >= 0):
        raise ValueError(
            f"CGACPolicy: mean_init_scale must be a finite number >= 0 (a factor on the actor's initial mean layer, "
            f"1 for the unscaled init, 0.01 for near-zero initial actions), got {mean_init_scale}."
        )
    if n_bins is not None and (isinstance(n_bins, bool) or not isinstance(n_bins, int) or n_bins < 2):
        raise ValueError(
            f"CGACPolicy: n_bins must be None (one Q-value per critic) or an integer >= 2 (bins of a categorical "
            f"critic, e.g. 101), got {n_bins!r}."
        )
    if isinstance(n_critics, bool) or not isinstance(n_critics, int) or n_critics < 1:
        raise ValueError(
            f"CGACPolicy: n_critics must be an integer >= 1 (the paper's twin critics: 2; one critic: no minimum in the "
            f"targets), got {n_critics!r}."
        )
    if actor_q_reduction not in ("min", "mean"):
        raise ValueError(f"CGACPolicy: actor_q_reduction must be 'min' or 'mean', got {actor_q_reduction!r}.")


def make_obs_normalizer(observation_space: spaces.Space) -> ObsNormalizer:
    """The in-policy observation normaliser of a Box or Dict observation space (``normalize_observations``)."""
    if isinstance(observation_space, spaces.Dict):
        return DictObsNormalizer(observation_space)
    if isinstance(observation_space, spaces.Box):
        return RunningObsNormalizer(observation_space.shape)
    raise ValueError(f"CGACPolicy: normalize_observations needs a Box or Dict observation space, got {observation_space}.")


class CGACPolicy(BasePolicy):
    """
    Policy class for CGAC: an actor and twin Q critics that are trained, plus a Polyak-averaged copy of
    each (the averaged actor acts in the environment and samples next actions, the target critic gives
    the value targets; paper Sec. 4.2, "Policy-Value Coupling"), and optionally a slower average of the actor that
    ``predict()`` acts with (``predict_actor``). They all live here so that ``policy.save()``/``load()`` keep them.

    :param observation_space: Observation space
    :param action_space: Action space
    :param lr_schedule: Learning rate schedule (the algorithm sets the actual learning rates)
    :param net_arch: Hidden layers, the same list for actor and critics, or ``dict(pi=[...], qf=[...])``
    :param activation_fn: Activation function (ELU in the paper)
    :param log_std_init: Initial log standard deviation of the actor (-1 in the paper's code)
    :param use_xavier_init: Whether to use Xavier-uniform weights and zero biases (the paper's code)
    :param mean_init_scale: Factor on the initial weights of the actor's mean layer: 1 keeps the initialisation
        above; a small value such as 0.01 makes the untrained actor's mean actions near zero, so that it starts from
        the env's "do nothing" (an Ant that stands rather than one that falls) instead of an arbitrary posture
    :param features_extractor_class: Features extractor to use
    :param features_extractor_kwargs: Keyword arguments to pass to the features extractor
    :param normalize_images: Whether to normalize images or not, dividing by 255.0
    :param optimizer_class: The optimizer to use, ``th.optim.Adam`` by default
    :param optimizer_kwargs: Additional keyword arguments, excluding the learning rate, to pass to the optimizer
        (Adam and AdamW get ``fused=True`` unless ``fused`` or ``foreach`` is given: one kernel per step)
    :param n_critics: Number of Q networks (the value targets use their minimum, paper Eq. 11, and the actor as
        ``actor_q_reduction`` says); 1: a single critic, whose targets have no minimum to take
    :param share_features_extractor: Whether actor and critic share the features extractor
    :param normalize_observations: Normalise observations with running statistics inside the policy, clipped at
        +-5 (the authors' code always does), so that no ``VecNormalize`` is needed; the statistics are updated
        from the collected observations and saved with the model (a Dict observation: each Box entry on its own)
    :param actor_keys: For a Dict observation, the keys the actor (and so ``predict()`` and exported policies)
        reads, e.g. ``["state"]``: what the robot senses (None: every key)
    :param critic_keys: For a Dict observation, the keys the critics read, e.g. ``["state", "privileged_state"]``
        (None: every key). With ``actor_keys`` this is an asymmetric actor-critic
    :param predict_actor: Whether to keep a third copy of the actor, ``actor_predict``, that ``predict()`` acts with
        (set by CGAC's ``predict_tau``, which averages it); False: ``predict()`` acts with the averaged actor
    :param critic_layer_norm: Whether the critics have a LayerNorm between each hidden layer and its activation
    :param n_bins: None: each critic outputs one Q-value (the paper's); a number such as 101: each outputs a
        categorical distribution over that many bins of a fixed symlog support, trained by cross-entropy to the
        targets' HL-Gauss distributions (``sb3_cgac.critics.HistogramSupport``: no per-task range to set)
    :param actor_q_reduction: How the actor loss reads the critics: ``"min"``, their minimum (paper Eq. 11), or
        ``"mean"``; the value targets always use the target critics' minimum
    """

    actor: Actor
    actor_avg: Actor
    actor_predict: Actor | None
    critic: CGACCritic
    critic_target: CGACCritic
    action_low: th.Tensor
    action_high: th.Tensor

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        net_arch: list[int] | dict[str, list[int]] | None = None,
        activation_fn: type[nn.Module] = nn.ELU,
        log_std_init: float = -1.0,
        use_xavier_init: bool = True,
        mean_init_scale: float = 1.0,
        features_extractor_class: type[BaseFeaturesExtractor] = FlattenExtractor,
        features_extractor_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
        n_critics: int = 2,
        share_features_extractor: bool = False,
        normalize_observations: bool = False,
        actor_keys: list[str] | None = None,
        critic_keys: list[str] | None = None,
        predict_actor: bool = False,
        critic_layer_norm: bool = False,
        n_bins: int | None = None,
        actor_q_reduction: str = "min",
    ):
        super().__init__(
            observation_space,
            action_space,
            features_extractor_class,
            features_extractor_kwargs,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            normalize_images=normalize_images,
            squash_output=True,
        )
        check_policy_arguments(self.action_space, mean_init_scale, n_bins, n_critics, actor_q_reduction)
        self.actor_q_reduction = actor_q_reduction
        if net_arch is None:
            net_arch = list(DEFAULT_NET_ARCH)
        actor_arch, critic_arch = get_actor_critic_arch(net_arch)
        self.net_arch = net_arch
        self.activation_fn = activation_fn
        self.use_xavier_init = use_xavier_init
        self.share_features_extractor = share_features_extractor
        self.normalize_observations = normalize_observations
        self.predict_actor = predict_actor
        self.actor_keys = self._check_keys("actor_keys", actor_keys)
        self.critic_keys = self._check_keys("critic_keys", critic_keys)
        if share_features_extractor and self.actor_keys != self.critic_keys:
            raise ValueError(
                "CGACPolicy: share_features_extractor=True needs the actor and the critics to read the same keys, got "
                f"actor_keys={actor_keys} and critic_keys={critic_keys}; set share_features_extractor=False."
            )
        self.obs_normalizer = make_obs_normalizer(self.observation_space) if normalize_observations else None
        net_args = {
            "observation_space": self.observation_space,
            "action_space": self.action_space,
            "activation_fn": activation_fn,
            "normalize_images": normalize_images,
        }
        self.actor_kwargs = {
            **net_args,
            "net_arch": actor_arch,
            "log_std_init": log_std_init,
            "use_xavier_init": use_xavier_init,
            "mean_init_scale": mean_init_scale,
        }
        self.critic_kwargs = {
            **net_args,
            "net_arch": critic_arch,
            "n_critics": n_critics,
            "share_features_extractor": share_features_extractor,
            "use_xavier_init": use_xavier_init,
            "layer_norm": critic_layer_norm,
            "n_bins": n_bins,
        }
        # The action bounds as tensors, for unscale_action_tensor (not saved: the action space gives them)
        assert isinstance(self.action_space, spaces.Box)
        self.register_buffer("action_low", th.as_tensor(self.action_space.low, dtype=th.float32), persistent=False)
        self.register_buffer("action_high", th.as_tensor(self.action_space.high, dtype=th.float32), persistent=False)
        self._build(lr_schedule)

    def _build(self, lr_schedule: Schedule) -> None:
        self.actor = self.make_actor()
        self.actor.optimizer = self.optimizer_class(  # type: ignore[call-arg]
            self.actor.parameters(), lr=lr_schedule(1), **self._optimizer_kwargs()
        )
        if self.share_features_extractor:
            self.critic = self.make_critic(features_extractor=self.actor.features_extractor)
            # The shared features extractor is trained by the actor loss only
            critic_parameters = [param for name, param in self.critic.named_parameters() if "features_extractor" not in name]
        else:
            self.critic = self.make_critic(features_extractor=None)
            critic_parameters = list(self.critic.parameters())
        self.critic.optimizer = self.optimizer_class(  # type: ignore[call-arg]
            critic_parameters, lr=lr_schedule(1), **self._optimizer_kwargs()
        )

        # Polyak-averaged copies, never trained by gradient and always in eval mode
        self.actor_avg = self.make_actor()
        self.actor_avg.load_state_dict(self.actor.state_dict())
        self.critic_target = self.make_critic(features_extractor=None)
        self.critic_target.load_state_dict(self.critic.state_dict())
        self.actor_predict = None
        if self.predict_actor:
            # Its initial weights are overwritten: building it must not draw from the RNG, so that a seed trains the
            # same networks with and without it
            with th.random.fork_rng(devices=[]):
                self.actor_predict = self.make_actor()
            self.actor_predict.load_state_dict(self.actor.state_dict())
        for averaged in (self.actor_avg, self.critic_target, self.actor_predict):
            if averaged is not None:
                averaged.requires_grad_(False)
                averaged.set_training_mode(False)
        # (averaged, trained) parameter lists of polyak_update, gathered once: module traversals cost more than the
        # small networks' ops
        actor: list[th.Tensor] = list(self.actor.parameters())
        self._polyak_pairs: list[tuple[list[th.Tensor], list[th.Tensor]]] = [
            (list(self.critic_target.parameters()), list(self.critic.parameters())),
            (list(self.actor_avg.parameters()), actor),
            ([] if self.actor_predict is None else list(self.actor_predict.parameters()), actor),
        ]

    @th.no_grad()
    def polyak_update(self, tau: float, policy_tau: float, predict_tau: float | None = None) -> None:
        """
        Move the averaged copies towards the trained networks (paper Sec. 4.2): ``target <- (1 - tau) * target +
        tau * online`` for the target critic, ``policy_tau`` for the averaged actor, ``predict_tau`` for
        ``actor_predict``; each network's parameters in one foreach call.
        """
        for (averaged, online), rate in zip(self._polyak_pairs, (tau, policy_tau, predict_tau), strict=True):
            if rate is not None and averaged:
                th._foreach_lerp_(averaged, online, rate)

    def _optimizer_kwargs(self) -> dict[str, Any]:
        # Adam's fused implementation (CPU and CUDA) takes a fraction of the per-tensor loop's time
        if self.optimizer_class in (th.optim.Adam, th.optim.AdamW) and not {"fused", "foreach"} & set(self.optimizer_kwargs):
            return {"fused": True, **self.optimizer_kwargs}
        return self.optimizer_kwargs

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            dict(
                net_arch=self.net_arch,
                activation_fn=self.activation_fn,
                log_std_init=self.actor_kwargs["log_std_init"],
                use_xavier_init=self.use_xavier_init,
                mean_init_scale=self.actor_kwargs["mean_init_scale"],
                lr_schedule=self._dummy_schedule,  # not needed to load the policy alone
                optimizer_class=self.optimizer_class,
                optimizer_kwargs=self.optimizer_kwargs,
                features_extractor_class=self.features_extractor_class,
                features_extractor_kwargs=self.features_extractor_kwargs,
                n_critics=self.critic_kwargs["n_critics"],
                share_features_extractor=self.share_features_extractor,
                normalize_observations=self.normalize_observations,
                actor_keys=self.actor_keys,
                critic_keys=self.critic_keys,
                predict_actor=self.predict_actor,
                critic_layer_norm=self.critic_kwargs["layer_norm"],
                n_bins=self.critic_kwargs["n_bins"],
                actor_q_reduction=self.actor_q_reduction,
            )
        )
        return data

    def _check_keys(self, name: str, keys: list[str] | None) -> list[str] | None:
        if keys is None:
            return None
        space = self.observation_space
        if not isinstance(space, spaces.Dict):
            raise ValueError(f"CGACPolicy: {name} needs a Dict observation space (MultiInputPolicy), got {space}.")
        unknown = [key for key in keys if key not in space.spaces]
        if unknown or not keys:
            raise ValueError(
                f"CGACPolicy: {name}={list(keys)} names {unknown or 'no key'}; the observation's keys are "
                f"{list(space.spaces)}."
            )
        return list(keys)

    def make_features_extractor(self, keys: list[str] | None = None) -> BaseFeaturesExtractor:
        """
        :param keys: The keys of a Dict observation that the extractor reads (None: all)
        :return: A features extractor, after the shared observation normalisation when there is one
        """
        if keys is None:
            features_extractor = super().make_features_extractor()
        else:
            assert isinstance(self.observation_space, spaces.Dict)
            features_extractor = DictKeysExtractor(
                self.observation_space, keys, self.features_extractor_class, self.features_extractor_kwargs
            )
        if self.obs_normalizer is None:
            return features_extractor
        return NormalizedFeaturesExtractor(self.observation_space, features_extractor, self.obs_normalizer)

    def update_obs_normalizer(self, obs: PyTorchObs, ok: th.Tensor, all_reduce: AllReduce | None = None) -> None:
        """
        Merge a batch of collected observations into the running statistics (no-op without normalisation).

        :param obs: Observations, one row per env
        :param ok: Which rows are usable (the others were non-finite and zeroed)
        :param all_reduce: With data-parallel training, the sum over the ranks: every rank merges all ranks' rows
        """
        if self.obs_normalizer is None:
            return
        self.obs_normalizer.update(obs, ok, all_reduce)  # type: ignore[arg-type]

    def make_actor(self, features_extractor: BaseFeaturesExtractor | None = None) -> Actor:
        features_extractor = features_extractor or self.make_features_extractor(self.actor_keys)
        actor_kwargs = self._update_features_extractor(self.actor_kwargs, features_extractor)
        return Actor(**actor_kwargs).to(self.device)

    def make_critic(self, features_extractor: BaseFeaturesExtractor | None = None) -> CGACCritic:
        features_extractor = features_extractor or self.make_features_extractor(self.critic_keys)
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        return CGACCritic(**critic_kwargs).to(self.device)

    def obs_to_tensor(self, observation: np.ndarray | dict[str, np.ndarray]) -> tuple[PyTorchObs, bool]:
        # predict() needs only the actor's keys of a Dict observation: the others may be left out
        if isinstance(observation, dict) and self.actor_keys is not None:
            missing = [key for key in self.actor_keys if key not in observation]
            if missing:
                raise ValueError(
                    f"CGACPolicy: the observation lacks the actor's keys {missing} (actor_keys={self.actor_keys})."
                )
        return super().obs_to_tensor(observation)

    def unscale_action_tensor(self, actions: th.Tensor) -> th.Tensor:
        """SB3's ``unscale_action`` on the policy's device: squashed actions in [-1, 1] to the action space's bounds."""
        low, high = self.action_low, self.action_high
        return low + (0.5 * (actions + 1.0) * (high - low))

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self._predict(obs, deterministic=deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        # The averaged actor is the behaviour policy (paper Sec. 4.2): predict() acts as training rollouts do, unless
        # a slower average is kept for it (CGAC's predict_tau)
        actor = self.actor_avg if self.actor_predict is None else self.actor_predict
        return actor(observation, deterministic)

    @th.no_grad()
    def target_q_value(self, obs: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """
        Minimum over the target critics (paper Eq. 11), used for the value targets (Eq. 9-10).

        :param obs: Observations, batch size B
        :param actions: Squashed actions, shape (B, action_dim)
        :return: Target Q-values of shape (B,)
        """
        return self.critic_target.q_values(obs, actions).min(dim=0).values

    def parameters_finite(self, *extra: th.Tensor) -> th.Tensor:
        """
        Whether the trained networks' parameters (and the ``extra`` tensors) are finite, in one foreach call: a boolean
        tensor on the device (read it with the other statistics: no host sync of its own).
        """
        # The averaged copies are convex combinations of these, so they need no check of their own. A norm is finite
        # exactly when its tensor is (up to overflow, itself a failure)
        tensors = (*self.actor.parameters(), *self.critic.parameters(), *extra)
        norms = th._foreach_norm([tensor.detach() for tensor in tensors])
        return th.stack(norms).isfinite().all()

    def set_training_mode(self, mode: bool) -> None:
        """
        Put the trained networks in training or evaluation mode (the averaged copies stay in evaluation mode).

        :param mode: if true, set to training mode, else set to evaluation mode
        """
        self.actor.set_training_mode(mode)
        self.critic.set_training_mode(mode)
        self.training = mode


MlpPolicy = CGACPolicy


class MultiInputPolicy(CGACPolicy):
    """
    Policy class for CGAC with Dict observations: ``CGACPolicy`` with a ``CombinedExtractor`` as default features
    extractor; ``actor_keys`` and ``critic_keys`` choose which keys the actor and the critics read.

    :param observation_space: Observation space (a Dict)
    :param action_space: Action space
    :param lr_schedule: Learning rate schedule (the algorithm sets the actual learning rates)
    :param kwargs: The other parameters of ``CGACPolicy``
    """

    def __init__(self, observation_space: spaces.Dict, action_space: spaces.Box, lr_schedule: Schedule, **kwargs: Any):
        kwargs.setdefault("features_extractor_class", CombinedExtractor)
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)
