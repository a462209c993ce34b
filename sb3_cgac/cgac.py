from typing import Any, ClassVar, TypeVar

import torch as th
from stable_baselines3.common.logger import configure as configure_logger
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule, TensorDict
from stable_baselines3.common.vec_env import VecEnv

from sb3_cgac.buffers import CGACRolloutBuffer, CGACSamples
from sb3_cgac.common.compat import upgrade_saved_attributes, upgrade_saved_defaults
from sb3_cgac.common.cuda_graphs import UpdateGraphs, plain_optimizer_states, set_learning_rate
from sb3_cgac.common.diagnostics import check_finite_parameters, read_statistics, total_grad_norm
from sb3_cgac.common.distributed import RANK_SEED_STRIDE, start_data_parallel, world
from sb3_cgac.hyperparameters import (
    CHECKED_ARGUMENTS,
    UpdateCost,
    check_action_space,
    check_batch_fits,
    check_hyperparameters,
    episode_horizon,
    horizon_gamma,
    parse_ent_coef,
    resolve_auto_hyperparameters,
    resolve_update_precision,
    warn_few_envs,
)
from sb3_cgac.losses import actor_loss, critic_loss, update_log_ent_coef
from sb3_cgac.policies import Actor, CGACCritic, CGACPolicy, MlpPolicy, MultiInputPolicy
from sb3_cgac.return_scale import ReturnScale
from sb3_cgac.window_algorithm import WindowOnPolicyAlgorithm

SelfCGAC = TypeVar("SelfCGAC", bound="CGAC")

# The learning rate of each optimizer as a multiple of learning_rate: alpha's is 10x the actor's (the paper's code)
LEARNING_RATE_FACTORS = {"actor": 1.0, "critic": 1.0, "ent_coef": 10.0}


class CGAC(WindowOnPolicyAlgorithm):
    """
    Critic-Gradient-based Actor-Critic (CGAC), an on-policy actor-critic for massively parallel simulators.
    Paper: "Practical Critic Gradient based Actor Critic for On-Policy Reinforcement Learning",
    Gurumurthy, Manchester and Kolter, L4DC 2023.

    Each iteration collects ``n_steps`` steps of every env with the *averaged actor* into a window of the last
    ``buffer_window`` steps, computes Q-GAE(lambda) targets from the *target critic* (Eq. 9-10), then runs
    ``critic_updates_per_step`` critic updates per collected step on uniform minibatches of the window, with an
    actor and alpha update (Eq. 7 and 12) and the Polyak updates of both averaged copies every ``policy_delay``
    critic updates. ``"auto"`` values resolve by device at construction (``sb3_cgac.hyperparameters``).

    :param policy: The policy model to use (MlpPolicy, MultiInputPolicy)
    :param env: The environment to learn from (if registered in Gym, can be str). Use many parallel envs.
    :param learning_rate: Adam's learning rate of the actor and critics, constant or a schedule of the progress
        remaining (e.g. the authors' decay ``LinearSchedule(2e-3, 1e-4, end_fraction)``); alpha's is 10x this rate
    :param n_steps: Number of new steps collected per env in each iteration
    :param buffer_window: Number of most recent steps per env kept in the buffer (paper: 32)
    :param batch_size: Minibatch size (``"auto"``: 512 on a CPU, the paper's 4096 on a GPU, at most the window)
    :param critic_updates_per_step: Critic updates per collected step (``"auto"``: 4 on a CPU; on a GPU 4 below
        1024 envs, from there on enough that each transition is sampled 8 times, at least the paper's 2)
    :param policy_delay: One actor and alpha update every ``policy_delay`` critic updates (paper: 2)
    :param gamma: Discount factor, or ``"auto"``: from the episodes' time limit ``T`` (the env's
        ``max_episode_steps``), ``(T/5 - 1) / (T/5)`` within [0.95, 0.995] (TD-MPC2's rule); 0.99 without one
    :param gae_lambda: lambda of the Q-GAE targets
    :param gae_horizon: Maximum number of reward terms in a Q-GAE target (None: the whole window; paper: 8 for
        SNU humanoid and AllegroHand)
    :param tau: Polyak coefficient of the target critic at every actor update (``"auto"``: 0.02 on a CPU; on a
        GPU the paper's 0.005 per 4096 new transitions, scaled to the number of envs)
    :param policy_tau: Polyak coefficient of the averaged actor, likewise (``"auto"``: 0.05; paper: 0.001)
    :param predict_tau: Polyak coefficient of a third copy of the actor that ``predict()`` acts with (training is
        unchanged); None: ``predict()`` acts with the averaged actor
    :param ent_coef: Entropy coefficient alpha: a float, or ``"auto"`` / ``"auto_<init>"`` to learn it (Eq. 12)
    :param target_entropy_beta: beta of the target entropy ``-beta * |A|`` (Eq. 12); the entropy schedules of
        ``sb3_cgac.callbacks`` (Eq. 13) change it during training
    :param ent_coef_monotone: Clamp of the learned alpha (Sec. 4.2): ``"above_target"`` keeps it from rising while
        the entropy is at or above its target; ``True`` is the paper's ``alpha = min(alpha_prev, alpha_new)``;
        ``False`` leaves it free (SAC)
    :param scale_rewards: Divide the rewards the critics learn from by ``max(std(G), max|G| / 5)`` of the envs'
        running discounted returns ``G`` (SimbaV2's scaling), so that their targets sit in a fixed range whatever the
        reward scale; the statistics are saved with the model (under torchrun, merged over the ranks), and the
        callbacks and logs see the env's rewards
    :param critic_loss: The scalar critics' regression loss (Eq. 8): ``"huber"``, the paper code's adaptive Huber
        loss (squared below 4x the minibatch's median error, linear above), or ``"mse"``, the squared error, which
        keeps the full gradient of a sparse reward's rare large targets (categorical critics use their cross-entropy)
    :param max_grad_norm: Gradient-norm clipping of the critic update (paper's code: 20)
    :param update_precision: ``"float32"``, ``"bfloat16"`` (the networks of the updates under autocast; losses,
        optimizers and collection stay float32), or ``"auto"``: bfloat16 on CPUs with AVX512-BF16 or AMX
    :param cuda_graphs: Replay the critic and actor updates as CUDA graphs (CUDA only; a warning elsewhere)
    :param rollout_buffer_class: Rollout buffer class to use (None: ``CGACRolloutBuffer``)
    :param rollout_buffer_kwargs: Keyword arguments to pass to the rollout buffer on creation
    :param stats_window_size: Window size for the rollout logging, specifying the number of episodes to average
        the reported success rate, mean episode length, and mean reward over
    :param tensorboard_log: the log location for tensorboard (if None, no logging)
    :param policy_kwargs: additional arguments to be passed to the policy on creation
    :param verbose: Verbosity level: 0 for no output, 1 for info messages, 2 for debug messages
    :param seed: Seed for the pseudo random generators
    :param device: Device (cpu, cuda, ...) on which the code should be run.
        Setting it to auto, the code will be run on the GPU if possible.
    :param _init_setup_model: Whether or not to build the network at the creation of the instance
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    actor: Actor
    actor_avg: Actor
    critic: CGACCritic
    critic_target: CGACCritic
    # Set by _setup_model, which resolves the "auto" of the constructor's arguments into numbers
    batch_size: int
    critic_updates_per_step: int
    tau: float
    policy_tau: float

    def __init__(
        self,
        policy: str | type[CGACPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 2e-3,
        n_steps: int = 1,
        buffer_window: int = 32,
        batch_size: int | str = "auto",
        critic_updates_per_step: int | str = "auto",
        policy_delay: int = 2,
        gamma: float | str = 0.99,
        gae_lambda: float = 0.95,
        gae_horizon: int | None = None,
        tau: float | str = "auto",
        policy_tau: float | str = "auto",
        predict_tau: float | None = None,
        ent_coef: str | float = "auto_0.1",
        target_entropy_beta: float = 1.0,
        ent_coef_monotone: bool | str = "above_target",
        scale_rewards: bool = False,
        critic_loss: str = "huber",
        max_grad_norm: float = 20.0,
        update_precision: str = "float32",
        cuda_graphs: bool = False,
        rollout_buffer_class: type[CGACRolloutBuffer] | None = None,
        rollout_buffer_kwargs: dict[str, Any] | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        arguments = dict(locals())  # the constructor's arguments, checked once the base class has set policy_kwargs
        super().__init__(
            policy,  # type: ignore[arg-type]
            env,
            learning_rate=learning_rate,
            n_steps=n_steps,
            gamma=gamma,  # type: ignore[arg-type]  # "auto" is resolved by _setup_model
            gae_lambda=gae_lambda,
            ent_coef=0.0,  # replaced below: CGAC's alpha may be a string
            vf_coef=0.0,
            max_grad_norm=max_grad_norm,
            use_sde=False,
            sde_sample_freq=-1,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            policy_kwargs=policy_kwargs,
            verbose=verbose,
            seed=seed,
            device=device,
            _init_setup_model=False,
        )
        self.ent_coef = ent_coef  # type: ignore[assignment]
        self.buffer_window = buffer_window
        self.policy_delay = policy_delay
        self.gae_horizon = gae_horizon
        # What the constructor was given; _setup_model resolves it into batch_size, critic_updates_per_step, tau, policy_tau
        self._requested_update_cost = (batch_size, critic_updates_per_step, tau, policy_tau)
        self.predict_tau = predict_tau
        self.target_entropy_beta = target_entropy_beta
        self.ent_coef_monotone = ent_coef_monotone
        self.scale_rewards = scale_rewards
        self.critic_loss = critic_loss
        self.update_precision = update_precision
        self.cuda_graphs = cuda_graphs
        self.rollout_buffer_class = rollout_buffer_class  # type: ignore[assignment]
        self.rollout_buffer_kwargs = rollout_buffer_kwargs or {}
        self.log_ent_coef: th.Tensor | None = None
        self.ent_coef_optimizer: th.optim.Optimizer | None = None

        predict_actor = self.policy_kwargs.get("predict_actor")
        check_hyperparameters(**{name: arguments[name] for name in CHECKED_ARGUMENTS}, predict_actor=predict_actor)
        if _init_setup_model:
            self._setup_model()
            check_batch_fits(self.batch_size, self.buffer_window, self.n_envs)
            warn_few_envs(self.n_envs)

    @staticmethod
    def _wrap_env(env: GymEnv, verbose: int = 0, monitor_wrapper: bool = True) -> VecEnv:
        # The one check of the action space, for every env (constructor, set_env, load), before SB3's terser checks
        check_action_space(env.action_space)
        return OnPolicyAlgorithm._wrap_env(env, verbose, monitor_wrapper)

    def _setup_model(self) -> None:
        upgrade_saved_attributes(self.__dict__)  # a model loaded from an sb3_cgac 0.1.0 file
        # The policy's defaults when the model was made: a later release's defaults do not change a saved model
        self.policy_defaults = upgrade_saved_defaults(self.__dict__, self.policy_class)
        self._setup_lr_schedule()
        self.set_random_seed(self.seed)
        # "auto" becomes the numbers for this device and env count. A loaded model keeps the numbers it was saved with:
        # SB3's load() sets them before it calls this method
        requested = [
            self.__dict__.get(name, value) for name, value in zip(UpdateCost._fields, self._requested_update_cost, strict=True)
        ]
        cost = resolve_auto_hyperparameters(
            *requested,
            n_envs=self.n_envs,
            buffer_window=self.buffer_window,
            policy_delay=self.policy_delay,
            device=self.device,
        )
        self.batch_size, self.critic_updates_per_step, self.tau, self.policy_tau = cost
        if self.gamma == "auto":  # a loaded model keeps the discount it was trained with
            self.gamma = horizon_gamma(episode_horizon(self.env))
        if self.scale_rewards:  # a loaded model keeps its statistics
            self.return_scale = (self.return_scale or ReturnScale(self.gamma)).to(self.device)

        buffer_class: type[CGACRolloutBuffer] = self.rollout_buffer_class or CGACRolloutBuffer  # type: ignore[assignment]
        self.rollout_buffer = buffer_class(
            self.buffer_window,
            self.observation_space,
            self.action_space,  # type: ignore[arg-type]
            device=self.device,
            n_envs=self.n_envs,
            gamma=self.gamma,
            gae_lambda=self.gae_lambda,
            gae_horizon=self.gae_horizon,
            **self.rollout_buffer_kwargs,
        )
        # The policy keeps the copy of the actor that predict() acts with exactly when predict_tau averages one
        policy_kwargs = {**self.policy_defaults, **self.policy_kwargs, "predict_actor": self.predict_tau is not None}
        self.policy = self.policy_class(  # type: ignore[assignment]
            self.observation_space, self.action_space, self.lr_schedule, **policy_kwargs
        )
        self.policy = self.policy.to(self.device)
        self._create_aliases()

        learn_alpha, init_alpha = parse_ent_coef(self.ent_coef)
        if learn_alpha:
            # Optimise log(alpha), as SB3's SAC does
            self.log_ent_coef = th.log(th.ones(1, device=self.device) * init_alpha).requires_grad_(True)
            lr = LEARNING_RATE_FACTORS["ent_coef"] * self.lr_schedule(1)
            self.ent_coef_optimizer = th.optim.Adam([self.log_ent_coef], lr=lr, fused=True)
        else:
            self.ent_coef_tensor = th.tensor(init_alpha, device=self.device)
        self._autocast_dtype = resolve_update_precision(self.update_precision, self.device)
        self._update_graphs = UpdateGraphs(
            self._critic_update, self._actor_update, lambda: list(self._optimizers().values()), self.device, self.cuda_graphs
        )

    def set_random_seed(self, seed: int | None = None) -> None:
        # Under torch.distributed each rank gets its own seed: its own envs and minibatches
        super().set_random_seed(None if seed is None else seed + world()[0] * RANK_SEED_STRIDE)

    def _create_aliases(self) -> None:
        self.actor = self.policy.actor
        self.actor_avg = self.policy.actor_avg
        self.critic = self.policy.critic
        self.critic_target = self.policy.critic_target
        # Parameter lists of the update loop, gathered once (module traversals cost more than the small nets' ops)
        self._critic_parameters: list[th.Tensor] = list(self.critic.parameters())
        self._actor_parameters: list[th.Tensor] = list(self.actor.parameters())

    def _optimizers(self) -> dict[str, th.optim.Optimizer]:
        """The optimizers of the updates by name: actor, critic and, when alpha is learned, ent_coef."""
        optimizers = {"actor": self.actor.optimizer, "critic": self.critic.optimizer}
        if self.ent_coef_optimizer is not None:
            optimizers["ent_coef"] = self.ent_coef_optimizer
        return optimizers

    def _ent_coef(self) -> th.Tensor:
        """The entropy coefficient alpha, on the device (no host sync)."""
        return self.ent_coef_tensor if self.log_ent_coef is None else th.exp(self.log_ent_coef.detach())

    def _critic_update(self, data: CGACSamples) -> dict[str, th.Tensor]:
        """One critic update (paper Eq. 8) on a minibatch; returns its statistics by name."""
        weight_sum = data.weights.sum().clamp_min(1.0)
        gather = self._parallel.gather if self._parallel is not None else None
        loss, q_mean = critic_loss(self.critic, *data, weight_sum, self._autocast_dtype, gather, self.critic_loss)
        self.critic.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self._parallel is not None:  # data-parallel: the mean gradient of every rank's minibatch
            self._parallel.average_gradients(self._critic_parameters)
        grad_norm = th.nn.utils.clip_grad_norm_(self._critic_parameters, self.max_grad_norm)
        self.critic.optimizer.step()
        return {"critic_loss": loss.detach(), "q_mean": q_mean, "critic_grad_norm": grad_norm}

    def _actor_update(self, target_entropy: th.Tensor, data: CGACSamples) -> dict[str, th.Tensor]:
        """
        One actor update (paper Eq. 7), then the entropy coefficient's (Eq. 12) and the Polyak updates of the averaged
        actor and the target critic; returns the update's statistics by name.
        """
        weight_sum = data.weights.sum().clamp_min(1.0)
        ent_coef = self._ent_coef()
        # Only dQ/da is needed for the actor loss: the critics' own gradients are not computed
        self.critic.set_q_requires_grad(False)
        loss, log_prob = actor_loss(
            self.actor,
            self.critic,
            data.observations,
            data.weights,
            weight_sum,
            ent_coef,
            self._autocast_dtype,
            self.policy.actor_q_reduction,
        )
        self.actor.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.critic.set_q_requires_grad(True)
        if self._parallel is not None:
            self._parallel.average_gradients(self._actor_parameters)
        grad_norm = total_grad_norm(self._actor_parameters)
        self.actor.optimizer.step()

        statistics = {"actor_loss": loss.detach(), "actor_grad_norm": grad_norm}
        statistics["entropy"] = -(log_prob * data.weights).sum() / weight_sum
        if self.ent_coef_optimizer is not None and self.log_ent_coef is not None:
            alpha_args = (log_prob, data.weights, weight_sum, target_entropy, self.ent_coef_monotone)
            average = self._parallel.mean if self._parallel is not None else None
            statistics["ent_coef_loss"] = update_log_ent_coef(
                self.log_ent_coef, self.ent_coef_optimizer, *alpha_args, average=average
            )
        self.policy.polyak_update(self.tau, self.policy_tau, self.predict_tau)
        return statistics

    def train(self) -> None:
        """Value targets of the new steps, then critic, actor, entropy-coefficient and Polyak updates on minibatches."""
        # Qbar of the new steps by the target critic, and the window's Q-GAE(lambda) targets (paper Eq. 9-11)
        self.rollout_buffer.compute_returns(self.policy.target_q_value)
        if self.rollout_buffer.n_transitions < self.batch_size:
            return  # the window does not hold a minibatch yet
        self.policy.set_training_mode(True)
        learning_rate = self.lr_schedule(self._current_progress_remaining)
        for name, optimizer in self._optimizers().items():
            # In place: CUDA graphs read it from the same memory
            set_learning_rate(optimizer, LEARNING_RATE_FACTORS[name] * learning_rate)
        if self._parallel is not None:  # an entropy schedule that follows each rank's rewards: one target for all
            self.target_entropy_beta = self._parallel.mean_float(self.target_entropy_beta)
        target_entropy = -self.target_entropy_beta * float(get_action_dim(self.action_space))
        target_entropy_tensor = th.full((), target_entropy, device=self.device)

        # Critic updates on uniform minibatches of the window; every policy_delay-th one also updates the actor,
        # alpha and the averaged copies
        critic_update, actor_update = self._update_graphs.steps()
        statistics = []
        for _ in range(self.critic_updates_per_step * self.n_steps):
            minibatch = self.rollout_buffer.sample(self.batch_size)
            statistics.append(critic_update(minibatch))
            self._n_updates += 1
            if self._n_updates % self.policy_delay == 0:
                statistics.append(actor_update(target_entropy_tensor, minibatch))
        self.policy.set_training_mode(False)

        # One read from the device per iteration (no host sync inside the update loop): finiteness and statistics
        finite = self.policy.parameters_finite(*([] if self.log_ent_coef is None else [self.log_ent_coef]))
        scalars = {"finite": finite, "ent_coef": self._ent_coef(), "std": th.exp(self.actor.log_std.detach()).mean()}
        if self.return_scale is not None:
            scalars["reward_scale"] = self.return_scale.scale()
        stats = read_statistics(scalars, statistics)
        check_finite_parameters(bool(stats.pop("finite")), self._n_updates)
        stats.update(target_entropy=target_entropy, beta=self.target_entropy_beta, tau=self.tau, policy_tau=self.policy_tau)
        stats.update(learning_rate=learning_rate)
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for key, value in stats.items():
            self.logger.record(f"train/{key}", value)

    def learn(
        self: SelfCGAC,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 100,
        tb_log_name: str = "CGAC",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfCGAC:
        check_batch_fits(self.batch_size, self.buffer_window, self.n_envs)
        if self._parallel is None and world()[1] > 1:  # under torchrun: every rank calls learn()
            self._parallel = start_data_parallel(self)
        if self._parallel is not None and self._parallel.rank != 0:  # rank 0 alone logs and shows progress
            progress_bar = False
            if not self._custom_logger:
                self.set_logger(configure_logger(None, []))
        return super().learn(
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )

    def _excluded_save_params(self) -> list[str]:
        # Aliases into the policy (saved with it), state rebuilt by _setup_model, and an attribute of sb3_cgac 0.1.0
        # files (sb3_cgac.common.compat)
        excluded = ["actor", "actor_avg", "critic", "critic_target", "_autocast_dtype", "_update_graphs"]
        excluded += ["_critic_parameters", "_actor_parameters", "gradient_ratio_average", "_requested_update_cost"]
        return [*super()._excluded_save_params(), *excluded]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts = ["policy", "actor.optimizer", "critic.optimizer"]
        if self.ent_coef_optimizer is not None:
            return [*state_dicts, "ent_coef_optimizer"], ["log_ent_coef"]
        return state_dicts, ["ent_coef_tensor"]

    def get_parameters(self) -> dict[str, dict]:
        params = super().get_parameters()
        plain_optimizer_states(params, ("actor.optimizer", "critic.optimizer", "ent_coef_optimizer"))
        return params

    def set_parameters(
        self, load_path_or_dict: str | TensorDict, exact_match: bool = True, device: th.device | str = "auto"
    ) -> None:
        with self._update_graphs.loading():
            super().set_parameters(load_path_or_dict, exact_match=exact_match, device=device)
