"""rsl_rl's own PPO driven from an SB3-style ``learn()`` (``RslPPO``), and its models as an SB3 policy."""

import contextlib
import io
import sys
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, PyTorchObs, Schedule
from stable_baselines3.common.utils import safe_mean

from sb3_cgac.vec_env import TorchVecEnv, episode_metrics

try:
    from rsl_rl.algorithms import PPO
    from tensordict import TensorDict
except ImportError as error:  # pragma: no cover - the extra is missing
    raise ImportError("sb3_cgac.rsl_rl needs rsl_rl: pip install 'sb3_cgac[rsl_rl]' (or pip install rsl-rl-lib).") from error

from sb3_cgac.rsl_rl.vec_env import BOX_GROUP, RslRlVecEnv, observation_groups

SelfRslPPO = TypeVar("SelfRslPPO", bound="RslPPO")

# RslPPO's policy_kwargs: the settings of rsl_rl's MLP models
MODEL_KWARGS = ("hidden_dims", "actor_hidden_dims", "critic_hidden_dims", "activation", "init_noise_std", "obs_normalization")


class RslActorCriticPolicy(BasePolicy):
    """
    rsl_rl's actor and critic models as an SB3 policy, for ``predict()`` (the deterministic action is the mean),
    saving and loading; the models are built by rsl_rl when ``RslPPO`` sets itself up.
    """

    def __init__(self, observation_space: spaces.Space, action_space: spaces.Box, actor: th.nn.Module, critic: th.nn.Module):
        super().__init__(observation_space, action_space)
        self.actor = actor
        self.critic = critic

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:  # type: ignore[override]
        return self._predict(obs, deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        groups = observation if isinstance(observation, dict) else {BOX_GROUP: observation}
        tensors = {key: value.float() for key, value in groups.items()}
        batch = TensorDict(tensors, batch_size=[len(next(iter(tensors.values())))], device=self.device)
        return self.actor(batch, stochastic_output=not deterministic)


class RslPPO(BaseAlgorithm):
    """
    rsl_rl's PPO with an SB3 interface. The defaults are rsl_rl's; the entries in ``hyperparams/rsl_ppo.yml`` use
    MuJoCo Playground's published rsl_rl settings.

    :param policy: ``"MlpPolicy"`` (Box observations) or ``"MultiInputPolicy"`` (Dict observations)
    :param env: The environment (an SB3 ``VecEnv`` or an env id)
    :param learning_rate: Adam's learning rate (the start value with the ``"adaptive"`` schedule); an SB3 schedule
        is read at the start of training, since rsl_rl's PPO keeps its own
    :param num_steps_per_env: Steps of every env per rollout
    :param num_learning_epochs: Passes over each rollout
    :param num_mini_batches: Minibatches per pass
    :param clip_param: PPO's ratio clipping
    :param gamma: Discount factor
    :param lam: GAE's lambda
    :param value_loss_coef: Weight of the value loss
    :param entropy_coef: Weight of the entropy bonus
    :param max_grad_norm: Gradient-norm clipping of the actor and the critic
    :param use_clipped_value_loss: Clip the value loss as the ratio is clipped
    :param schedule: ``"adaptive"`` (the learning rate follows the KL divergence to ``desired_kl``) or ``"fixed"``
    :param desired_kl: The KL target of the adaptive schedule
    :param actor_keys: Keys of a Dict observation the actor reads (None: every key)
    :param critic_keys: Keys the critic reads (None: every key), e.g. ``["privileged_state"]``: an asymmetric critic
    :param policy_kwargs: The models' settings: ``hidden_dims`` (or ``actor_hidden_dims`` / ``critic_hidden_dims``),
        ``activation``, ``init_noise_std``, ``obs_normalization`` (rsl_rl's empirical normalisation)
    :param tensorboard_log: The log location for tensorboard (if None, no logging)
    :param verbose: Verbosity level: 0 no output, 1 info messages (such as device or wrappers used)
    :param seed: Seed for the pseudo random generators
    :param device: Device (cpu, cuda, ...) on which the code should be run
    :param _init_setup_model: Whether or not to build the network at the creation of the instance
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {  # type: ignore[misc]
        "MlpPolicy": RslActorCriticPolicy,
        "MultiInputPolicy": RslActorCriticPolicy,
    }
    policy: RslActorCriticPolicy

    def __init__(
        self,
        policy: str | type[RslActorCriticPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 1e-3,
        num_steps_per_env: int = 24,
        num_learning_epochs: int = 5,
        num_mini_batches: int = 4,
        clip_param: float = 0.2,
        gamma: float = 0.99,
        lam: float = 0.95,
        value_loss_coef: float = 1.0,
        entropy_coef: float = 0.01,
        max_grad_norm: float = 1.0,
        use_clipped_value_loss: bool = True,
        schedule: str = "adaptive",
        desired_kl: float = 0.01,
        actor_keys: list[str] | None = None,
        critic_keys: list[str] | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        tensorboard_log: str | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        super().__init__(
            policy,
            env,
            learning_rate=learning_rate,
            policy_kwargs=policy_kwargs,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            support_multi_env=True,
            seed=seed,
            supported_action_spaces=(spaces.Box,),
        )
        self.num_steps_per_env = num_steps_per_env
        self.algorithm_kwargs = dict(
            num_learning_epochs=num_learning_epochs,
            num_mini_batches=num_mini_batches,
            clip_param=clip_param,
            gamma=gamma,
            lam=lam,
            value_loss_coef=value_loss_coef,
            entropy_coef=entropy_coef,
            max_grad_norm=max_grad_norm,
            use_clipped_value_loss=use_clipped_value_loss,
            schedule=schedule,
            desired_kl=desired_kl,
        )
        self.actor_keys = actor_keys
        self.critic_keys = critic_keys
        if _init_setup_model:
            self._setup_model()

    def _observation_groups(self) -> dict[str, list[str]]:
        if not isinstance(self.observation_space, spaces.Dict):
            if self.actor_keys or self.critic_keys:
                raise ValueError("RslPPO: actor_keys and critic_keys select keys of a Dict observation; this one is a Box.")
            return {"actor": [BOX_GROUP], "critic": [BOX_GROUP]}
        keys = list(self.observation_space.spaces)
        groups = {"actor": self.actor_keys or keys, "critic": self.critic_keys or keys}
        for role, chosen in groups.items():
            unknown = sorted(set(chosen) - set(keys))
            if unknown:
                raise ValueError(f"RslPPO: {role}_keys {unknown} are not keys of the observation, which has {keys}.")
        return groups

    def _train_config(self) -> dict[str, Any]:
        """rsl_rl's training configuration (its ``OnPolicyRunner`` format) of these settings."""
        models = dict(self.policy_kwargs)
        unknown = sorted(set(models) - set(MODEL_KWARGS))
        if unknown:
            raise ValueError(
                f"RslPPO: unknown policy_kwargs {unknown}; it takes hidden_dims (or actor_hidden_dims and "
                "critic_hidden_dims), activation, init_noise_std and obs_normalization."
            )
        hidden = models.get("hidden_dims", [256, 256, 256])
        shared = dict(class_name="MLPModel", activation=models.get("activation", "elu"))
        shared["obs_normalization"] = models.get("obs_normalization", False)
        distribution = dict(class_name="GaussianDistribution", init_std=models.get("init_noise_std", 1.0))
        return {
            "algorithm": dict(class_name="PPO", learning_rate=self.lr_schedule(1.0), **self.algorithm_kwargs),
            "actor": dict(shared, hidden_dims=models.get("actor_hidden_dims", hidden), distribution_cfg=distribution),
            "critic": dict(shared, hidden_dims=models.get("critic_hidden_dims", hidden)),
            "obs_groups": self._observation_groups(),
            "num_steps_per_env": self.num_steps_per_env,
            "multi_gpu": None,
        }

    def _setup_model(self) -> None:
        self._setup_lr_schedule()
        self.set_random_seed(self.seed)
        assert self.env is not None
        self.rsl_env = RslRlVecEnv(self.env, self.device)
        sample = (
            {key: np.stack([space.sample()]) for key, space in self.observation_space.spaces.items()}
            if isinstance(self.observation_space, spaces.Dict)
            else np.stack([self.observation_space.sample()])
        )
        obs = observation_groups(sample, self.device)  # type: ignore[arg-type]
        # rsl_rl's storage is sized from the observation batch: one of num_envs rows
        obs = obs.expand(self.n_envs).clone()
        # rsl_rl prints the models it builds: only when verbose
        with contextlib.redirect_stdout(sys.stdout if self.verbose >= 1 else io.StringIO()):
            self.alg = PPO.construct_algorithm(obs, self.rsl_env, self._train_config(), str(self.device))
        assert isinstance(self.action_space, spaces.Box)
        self.policy = RslActorCriticPolicy(self.observation_space, self.action_space, self.alg.actor, self.alg.critic)
        self.policy.to(self.device)

    def learn(
        self: SelfRslPPO,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 1,
        tb_log_name: str = "RslPPO",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfRslPPO:
        """
        rsl_rl's training loop (``OnPolicyRunner.learn``): rollouts of ``num_steps_per_env`` steps, returns,
        update; SB3's callbacks see every env step and may stop training.
        """
        iteration = 0
        total_timesteps, callback = self._setup_learn(
            total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar
        )
        assert self._last_obs is not None
        if self._last_obs is not self.rsl_env.last_obs:  # a reset by _setup_learn
            self.rsl_env.set_observations(self._last_obs)  # type: ignore[arg-type]
        callback.on_training_start(locals(), globals())
        while self.num_timesteps < total_timesteps:
            if not self.collect_rollout(callback):
                break
            iteration += 1
            self._update_current_progress_remaining(self.num_timesteps, total_timesteps)
            # As SB3's on-policy loop: the logs are dumped before the update, whose train/* values wait for the next
            if log_interval is not None and iteration % log_interval == 0:
                self.dump_logs(iteration)
            self.train()
        callback.on_training_end()
        return self

    def collect_rollout(self, callback: Any) -> bool:
        """One rollout into rsl_rl's storage; False if a callback stopped training."""
        obs = self.rsl_env.get_observations()
        self.alg.storage.clear()
        # predict() (an evaluation) leaves the models in eval mode, where rsl_rl's normalisers stop learning
        self.alg.train_mode()
        callback.on_rollout_start()
        tensor_env = self.env if isinstance(self.env, TorchVecEnv) else None
        with th.inference_mode():
            for _ in range(self.num_steps_per_env):
                actions = self.alg.act(obs)
                obs, rewards, dones, extras = self.rsl_env.step(actions)
                self.alg.process_env_step(obs, rewards, dones, extras)
                self.num_timesteps += self.n_envs
                if tensor_env is None:
                    self._update_info_buffer(self.rsl_env.last_infos, dones.cpu().numpy().astype(bool))
                self._last_obs = self.rsl_env.last_obs  # type: ignore[assignment]
                callback.update_locals(locals())
                if not callback.on_step():
                    return False
            self.alg.compute_returns(obs)
        if tensor_env is not None:  # one host read of the rollout's finished episodes
            self.ep_info_buffer.extend(tensor_env.pop_episodes())  # type: ignore[union-attr]
        callback.on_rollout_end()
        return True

    def train(self) -> None:
        """rsl_rl's PPO update of the stored rollout; its losses logged as ``train/*``."""
        losses = self.alg.update()
        self._n_updates += self.alg.num_learning_epochs * self.alg.num_mini_batches
        for key, value in losses.items():
            self.logger.record(f"train/{key}_loss" if key != "entropy" else "train/entropy", value)
        self.logger.record("train/learning_rate", self.alg.learning_rate)
        self.logger.record("train/std", self.alg.get_policy().output_std.mean().item())
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")

    def dump_logs(self, iteration: int = 0) -> None:
        self.logger.record("time/iterations", iteration, exclude="tensorboard")
        if self.ep_info_buffer:
            self.logger.record("rollout/ep_rew_mean", safe_mean([episode["r"] for episode in self.ep_info_buffer]))
            self.logger.record("rollout/ep_len_mean", safe_mean([episode["l"] for episode in self.ep_info_buffer]))
            for key, value in episode_metrics(self.ep_info_buffer).items():
                self.logger.record(f"rollout/ep_{key}_mean", value)
        self.logger.record("time/total_timesteps", self.num_timesteps, exclude="tensorboard")
        self.logger.dump(step=self.num_timesteps)

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "alg", "rsl_env", "_last_obs"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        return ["policy", "alg.optimizer"], []
