import warnings
from collections.abc import Callable
from typing import Any, ClassVar, TypeVar

from sb3_cgac.buffers import (
    CGACRolloutBuffer,
    CGACSamples,
    observations_to_tensor,
    samples_from_tensors,
    samples_to_tensors,
    split_episode_ends,
)
from sb3_cgac.callbacks import ENTROPY_SCHEDULES, EntropyScheduleCallback, with_entropy_schedule
from sb3_cgac.cuda_graphs import (
    GraphedStep,
    check_capturable,
    keep_optimizer_tensors,
    prepare_optimizers_for_capture,
    release_optimizers_from_capture,
    release_param_group,
    restore_optimizer_tensors,
    set_learning_rate,
)
from sb3_cgac.hyperparameters import (
    FEW_ENVS,
    check_action_space,
    check_hyperparameters,
    decayed_learning_rate,
    parse_ent_coef,
    resolve_batch_size,
    resolve_critic_updates_per_step,
    resolve_update_precision,
    scaled_polyak_rates,
    warn_few_envs,
    warn_many_critic_updates,
    with_predict_actor,
)
from sb3_cgac.losses import actor_loss, behaviour_kl, critic_loss, outlier_clipped_actor_loss, update_log_ent_coef
from sb3_cgac.policies import Actor, CGACCritic, CGACPolicy, MlpPolicy, MultiInputPolicy
from sb3_cgac.wrappers import warn_synchronised_resets

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, PyTorchObs, Schedule, TensorDict
from stable_baselines3.common.utils import FloatSchedule
from stable_baselines3.common.vec_env import VecEnv

SelfCGAC = TypeVar("SelfCGAC", bound="CGAC")


class CGAC(OnPolicyAlgorithm):
    """
    Critic-Gradient-based Actor-Critic (CGAC), an on-policy actor-critic for massively parallel simulators.
    Paper: "Practical Critic Gradient based Actor Critic for On-Policy Reinforcement Learning",
    Gurumurthy, Manchester and Kolter, L4DC 2023.

    Each iteration collects ``n_steps`` steps of every env with the *averaged actor* into a window of the last
    ``buffer_window`` steps, computes Q-GAE(lambda) targets from the *target critic* (Eq. 9-10), then runs
    ``critic_updates_per_step`` critic updates per collected step on uniform minibatches of the window, with an
    actor and entropy-coefficient update (SAC-style, Eq. 7 and 12) and the Polyak updates of both averaged copies
    every ``policy_delay`` critic updates. The defaults are the paper's schedule (one new step per iteration, a
    32-step window, two critic updates per step and an actor update on every second one), with four critic updates per
    step below 1024 envs; ``n_steps == buffer_window`` is PPO-like.

    :param policy: The policy model to use (MlpPolicy, MultiInputPolicy)
    :param env: The environment to learn from (if registered in Gym, can be str). Use many parallel envs.
    :param learning_rate: Learning rate of the actor (Adam), constant or a function of the progress
        remaining (from 1 to 0); also of the critic and entropy coefficient unless given separately
    :param critic_learning_rate: Learning rate of the critics (None: ``learning_rate``)
    :param ent_coef_learning_rate: Learning rate of the entropy coefficient (None: 10x ``learning_rate``,
        as in the paper's code)
    :param final_learning_rate: Learning rate reached by a linear decay of the actor and critic learning rates
        over ``lr_decay_iterations`` iterations (the authors' code: 2e-3 to 1e-4 over 20k); None: no decay. Alpha's
        learning rate does not decay, as in the authors' code, unless ``decay_ent_coef_learning_rate`` is set.
    :param lr_decay_iterations: Length of that decay in iterations (one iteration collects ``n_steps`` steps of
        every env and runs its updates)
    :param decay_ent_coef_learning_rate: Scale alpha's learning rate by the factor of the actor rate's decay (not in
        the authors' code, where alpha's rate keeps its initial value, 200x the final actor rate with their values).
        Adam moves log alpha by about its learning rate per update whatever the entropy error, so an undecayed rate
        lets alpha wind down by orders of magnitude late in training, and climb back as fast. Needs
        ``final_learning_rate`` and a learned alpha
    :param n_steps: Number of new steps collected per env in each iteration
    :param buffer_window: Number of most recent steps per env kept in the buffer (paper: 32)
    :param batch_size: Minibatch size (None: the paper's 4096, or the whole window when it holds fewer
        transitions). Updates start once the window holds ``batch_size`` transitions.
    :param critic_updates_per_step: Critic updates per collected step. None: 4 below 1024 envs (each step of few
        envs brings little new data; with the paper's 2 the bare defaults at 64 envs learned Pendulum-v1 more slowly
        and ended one of ten seeds in a dip); from 1024 envs on, the smallest count, at least the paper's 2, that
        samples each collected transition 8 times on average (``ceil(8 * n_envs / batch_size)``: with the batch of
        4096, 2 at 1024 envs, 4 at 2048, 8 at 4096, where the paper's 2 did not learn Pendulum-v1; a warning when a
        ``batch_size`` below 4096 makes it larger than that). Pass 2 for the paper's count
    :param policy_delay: One actor and entropy-coefficient update every ``policy_delay`` critic updates (paper: 2)
    :param gamma: Discount factor
    :param gae_lambda: lambda of the Q-GAE targets
    :param gae_horizon: Maximum number of reward terms in a Q-GAE target (None: the whole window;
        the paper uses 8 for SNU humanoid and AllegroHand)
    :param refresh_target_values: Before every iteration's updates, draw the next actions of the whole window again
        from the averaged actor and evaluate Qbar of every step with the current target critic (not in the paper,
        whose code evaluates Qbar once per transition, when it is added: at tau_Q = 0.005 per iteration its target
        critic barely moves over a 32-step window, while with fewer envs and more updates per step it moves several
        times faster and the stored values of the window's older steps go stale). Costs one forward pass of the
        averaged actor and the target critics over the window per iteration
    :param tau: Polyak coefficient of the target critic at every actor update (1: no averaging). None: the paper's
        tau_Q = 0.005 per 4096 new transitions, scaled to the ``m = n_envs * policy_delay / critic_updates_per_step``
        new transitions per actor update here (with the resolved ``critic_updates_per_step``) as
        ``1 - (1 - 0.005) ** sqrt(4096 / m)`` (0.055 at 64 envs with the default 4 critic updates per step)
    :param policy_tau: Polyak coefficient of the averaged actor at every actor update (1: no averaging). None: the
        paper's tau_pi = 0.001 scaled the same way (0.011 at 64 envs)
    :param predict_tau: Polyak coefficient, at every actor update, of a third copy of the actor that ``predict()``
        (evaluation, deployment) acts with; training is unchanged: the averaged actor of ``policy_tau`` still
        collects the data and draws the next actions. None (default): ``predict()`` acts with the averaged actor.
        A slow rate (the paper's tau_pi, 0.001) averages the trained actor over the last thousands of updates, where
        the fast averaged actor of entries tuned for few envs follows its swings; as it starts from the untrained
        actor (weight ``(1 - predict_tau) ** n`` after ``n`` actor updates), it is meant for long runs
    :param ent_coef: Entropy coefficient alpha: a float for a fixed value, or ``"auto"`` / ``"auto_<init>"``
        to learn it SAC-style (paper Eq. 12; the paper starts at 0.1)
    :param target_entropy_beta: beta of the target entropy ``-beta * |A|`` when learning alpha (Eq. 12);
        the entropy schedules change it during training
    :param ent_coef_monotone: Clamp of the learned alpha (paper Sec. 4.2): ``"above_target"`` (default) keeps
        alpha from increasing while the policy's entropy is at or above its target, and lets it rise only to bring
        an entropy that fell below the target back up, so exploration cannot lock; ``True`` is the paper's exact
        clamp ``alpha = min(alpha_prev, alpha_new)`` (alpha never increases); ``False`` leaves alpha free (SAC)
    :param entropy_schedule: Schedule of beta: ``"reward"`` (the paper's Eq. 13, see ``RewardEntropySchedule``),
        ``"progress"`` (linear in training progress, see ``ProgressEntropySchedule``) or None (fixed beta)
    :param entropy_schedule_kwargs: Keyword arguments of the entropy schedule callback
    :param critic_loss: ``"huber"`` (the paper's code: squared error below 4x the batch median of
        ``|Q - Y|``, linear above) or ``"mse"``
    :param max_grad_norm: Gradient-norm clipping of the critic update (paper's code: 20)
    :param actor_max_grad_norm: Gradient-norm clipping of the actor update (None: no clipping, as in the paper)
    :param clip_actor_gradient_outliers: Clip outliers of dQ/da in the actor update, as the paper's code can:
        when the mean over action dims of max|g| / median|g| exceeds twice its running average, each dim of
        dQ/da is clamped to its [50th, 95th] percentile range over the batch
    :param behaviour_kl_coef: Weight of a penalty ``KL(averaged actor || actor)`` in the actor loss (not in the
        paper; 0: off): it keeps the actor near the actions the critics were fitted to
    :param compile_updates: ``torch.compile`` the critic and actor losses: True, or a dict of its keyword arguments
        (a C++ compiler is needed on CPU; the outlier-clipped actor loss stays uncompiled)
    :param update_precision: ``"float32"``, or ``"bfloat16"``: the update's networks under bfloat16 autocast (CUDA,
        or CPUs with AVX512-BF16 or AMX; the critics' output layer, losses, optimizers, collection and the
        outlier-clipped actor loss stay float32), or ``"auto"``: bfloat16 on CPUs that have it in hardware, float32
        elsewhere (other CPUs emulate bfloat16; on CUDA it was no faster in eager mode), resolved again when a saved
        model is loaded
    :param cuda_graphs: Capture the critic update and the actor update (with its entropy-coefficient and Polyak
        updates) as CUDA graphs after 3 eager steps, and replay them: one launch instead of hundreds of small kernels
        per step, the same arithmetic (``sb3_cgac.cuda_graphs``). CUDA only (ignored with a warning elsewhere); not
        with ``compile_updates`` or ``clip_actor_gradient_outliers``, and the optimizers need a ``capturable`` option
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
    policy: CGACPolicy  # type: ignore[assignment]
    rollout_buffer: CGACRolloutBuffer  # type: ignore[assignment]
    actor: Actor
    actor_avg: Actor
    critic: CGACCritic
    critic_target: CGACCritic

    def __init__(
        self,
        policy: str | type[CGACPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 2e-3,
        critic_learning_rate: float | Schedule | None = None,
        ent_coef_learning_rate: float | Schedule | None = None,
        final_learning_rate: float | None = None,
        lr_decay_iterations: int = 20_000,
        decay_ent_coef_learning_rate: bool = False,
        n_steps: int = 1,
        buffer_window: int = 32,
        batch_size: int | None = None,
        critic_updates_per_step: int | None = None,
        policy_delay: int = 2,
        gamma: float = 0.99,
        gae_lambda: float = 0.95,
        gae_horizon: int | None = None,
        refresh_target_values: bool = False,
        tau: float | None = None,
        policy_tau: float | None = None,
        predict_tau: float | None = None,
        ent_coef: str | float = "auto_0.1",
        target_entropy_beta: float = 1.0,
        ent_coef_monotone: bool | str = "above_target",
        entropy_schedule: str | None = None,
        entropy_schedule_kwargs: dict[str, Any] | None = None,
        critic_loss: str = "huber",
        max_grad_norm: float = 20.0,
        actor_max_grad_norm: float | None = None,
        clip_actor_gradient_outliers: bool = False,
        behaviour_kl_coef: float = 0.0,
        compile_updates: bool | dict[str, Any] = False,
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
        super().__init__(
            policy,  # type: ignore[arg-type]
            env,
            learning_rate=learning_rate,
            n_steps=n_steps,
            gamma=gamma,
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
        self.critic_learning_rate = critic_learning_rate
        self.ent_coef_learning_rate = ent_coef_learning_rate
        self.final_learning_rate = final_learning_rate
        self.lr_decay_iterations = lr_decay_iterations
        self.decay_ent_coef_learning_rate = decay_ent_coef_learning_rate
        self.buffer_window = buffer_window
        self.batch_size = batch_size
        self.critic_updates_per_step = critic_updates_per_step
        self.policy_delay = policy_delay
        self.gae_horizon = gae_horizon
        self.refresh_target_values = refresh_target_values
        self.tau = tau
        self.policy_tau = policy_tau
        self.predict_tau = predict_tau
        self.target_entropy_beta = target_entropy_beta
        self.ent_coef_monotone = ent_coef_monotone
        self.entropy_schedule = entropy_schedule
        self.entropy_schedule_kwargs = entropy_schedule_kwargs or {}
        self.critic_loss = critic_loss
        self.actor_max_grad_norm = actor_max_grad_norm
        self.clip_actor_gradient_outliers = clip_actor_gradient_outliers
        self.behaviour_kl_coef = behaviour_kl_coef
        self.compile_updates = compile_updates
        self.update_precision = update_precision
        self.cuda_graphs = cuda_graphs
        self.rollout_buffer_class = rollout_buffer_class  # type: ignore[assignment]
        self.rollout_buffer_kwargs = rollout_buffer_kwargs or {}
        self.log_ent_coef: th.Tensor | None = None
        self.ent_coef_optimizer: th.optim.Optimizer | None = None
        # Collection state: actions already sampled for `_last_obs`, and the `_last_obs` the buffer ends with
        self._pending_actions: th.Tensor | None = None
        self._rollout_obs: Any = None
        self._entropy_schedule_callback: EntropyScheduleCallback | None = None
        self._warned_synchronised_resets = False

        self._check_hyperparameters()
        if _init_setup_model:
            self._setup_model()
            warn_few_envs(self.n_envs)
            warn_many_critic_updates(self.critic_updates_per_step, self.n_envs, self.batch_size, self._critic_updates_per_step)

    @staticmethod
    def _wrap_env(env: GymEnv, verbose: int = 0, monitor_wrapper: bool = True) -> VecEnv:
        # The one check of the action space, for every env (constructor, set_env, load), before SB3's terser checks
        check_action_space(env.action_space)
        return OnPolicyAlgorithm._wrap_env(env, verbose, monitor_wrapper)

    def _check_hyperparameters(self) -> None:
        names = ["n_steps", "buffer_window", "critic_updates_per_step", "policy_delay", "batch_size", "gae_horizon", "tau"]
        names += ["policy_tau", "gamma", "gae_lambda", "lr_decay_iterations", "final_learning_rate", "max_grad_norm"]
        names += ["behaviour_kl_coef", "ent_coef", "ent_coef_monotone", "entropy_schedule", "entropy_schedule_kwargs"]
        names += ["critic_loss", "update_precision", "compile_updates", "cuda_graphs", "clip_actor_gradient_outliers"]
        names += ["refresh_target_values", "predict_tau", "decay_ent_coef_learning_rate"]
        check_hyperparameters(**{name: getattr(self, name) for name in names}, entropy_schedules=tuple(ENTROPY_SCHEDULES))

    def _setup_model(self) -> None:
        self._setup_lr_schedule()
        self.critic_lr_schedule = FloatSchedule(
            self.learning_rate if self.critic_learning_rate is None else self.critic_learning_rate
        )
        self.ent_coef_lr_schedule = None if self.ent_coef_learning_rate is None else FloatSchedule(self.ent_coef_learning_rate)
        self.set_random_seed(self.seed)
        self._batch_size = resolve_batch_size(self.batch_size, self.buffer_window, self.n_envs)
        self._critic_updates_per_step = resolve_critic_updates_per_step(
            self.critic_updates_per_step, self.n_envs, self._batch_size
        )
        self._tau, self._policy_tau = scaled_polyak_rates(
            self.tau, self.policy_tau, self.n_envs, self.policy_delay, self._critic_updates_per_step
        )
        self._setup_update_functions()

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
        self.policy_kwargs = with_predict_actor(self.policy_kwargs, self.predict_tau)
        self.policy = self.policy_class(  # type: ignore[assignment]
            self.observation_space, self.action_space, self.lr_schedule, **self.policy_kwargs
        )
        self.policy = self.policy.to(self.device)
        self._create_aliases()

        learn_alpha, init_alpha = parse_ent_coef(self.ent_coef)
        if learn_alpha:
            # Optimise log(alpha), as SB3's SAC does
            self.log_ent_coef = th.log(th.ones(1, device=self.device) * init_alpha).requires_grad_(True)
            self.ent_coef_optimizer = th.optim.Adam([self.log_ent_coef], lr=10 * self.lr_schedule(1), fused=True)
        else:
            self.ent_coef_tensor = th.tensor(init_alpha, device=self.device)
        # Running average of the max/median ratio of dQ/da (actor-gradient outlier clipping); the paper's code starts at 100
        self.gradient_ratio_average = th.tensor(100.0, device=self.device)
        if self._use_cuda_graphs:
            check_capturable(self._optimizers())

    def _setup_update_functions(self) -> None:
        self._autocast_dtype = resolve_update_precision(self.update_precision, self.device)
        if self.verbose >= 1 and self.update_precision == "auto":
            print(f"update_precision='auto': updates in {'bfloat16' if self._autocast_dtype else 'float32'}")
        self._critic_loss_fn, self._actor_loss_fn = critic_loss, actor_loss
        if self.compile_updates:
            compile_kwargs = self.compile_updates if isinstance(self.compile_updates, dict) else {}
            self._critic_loss_fn = th.compile(critic_loss, **compile_kwargs)
            self._actor_loss_fn = th.compile(actor_loss, **compile_kwargs)
        self._graphed_updates: tuple[GraphedStep, GraphedStep] | None = None  # captured at the first updates
        if self.cuda_graphs and self.device.type != "cuda":
            warnings.warn(
                f"CGAC: cuda_graphs=True has no effect on device {self.device}: the updates run eagerly.", stacklevel=2
            )
        space = self.observation_space
        self._obs_keys = list(space.spaces) if isinstance(space, spaces.Dict) else None

    def _create_aliases(self) -> None:
        self.actor = self.policy.actor
        self.actor_avg = self.policy.actor_avg
        self.critic = self.policy.critic
        self.critic_target = self.policy.critic_target
        # Parameter lists of the update loop, gathered once (module traversals cost more than the small nets' ops)
        self._critic_parameters: list[th.Tensor] = list(self.critic.parameters())
        self._actor_parameters: list[th.Tensor] = list(self.actor.parameters())
        self._critic_target_parameters: list[th.Tensor] = list(self.critic_target.parameters())
        self._actor_avg_parameters: list[th.Tensor] = list(self.actor_avg.parameters())
        actor_predict = self.policy.actor_predict
        self._actor_predict_parameters: list[th.Tensor] = [] if actor_predict is None else list(actor_predict.parameters())

    def _init_callback(self, callback: MaybeCallback, progress_bar: bool = False) -> BaseCallback:
        if self.entropy_schedule is not None:
            # The schedule named by the `entropy_schedule` hyperparameter runs first, before the user's callbacks
            if self._entropy_schedule_callback is None:
                self._entropy_schedule_callback = ENTROPY_SCHEDULES[self.entropy_schedule](**self.entropy_schedule_kwargs)
            callback = with_entropy_schedule(callback, self._entropy_schedule_callback, self.entropy_schedule)
        return super()._init_callback(callback, progress_bar)

    def _start_rollout(self, buffer: CGACRolloutBuffer) -> None:
        # The window's trajectories end where `_last_obs` does not continue them (first call, env reset,
        # set_env, load): start a new window from `_last_obs`.
        obs, ok = observations_to_tensor(self._last_obs, self.device)
        buffer.reset()
        buffer.set_current_obs(obs, ok)
        self.policy.update_obs_normalizer(obs, ok)
        with th.inference_mode():
            self._pending_actions = self.actor_avg.sample(obs, 1)[0]
        self._rollout_obs = self._last_obs

    def collect_rollouts(  # type: ignore[override]
        self,
        env: VecEnv,
        callback: BaseCallback,
        rollout_buffer: CGACRolloutBuffer,
        n_rollout_steps: int,
    ) -> bool:
        """
        Collect ``n_rollout_steps`` steps of every env with the averaged actor into the window (the value targets
        are computed at the start of ``train()``). One forward pass of the averaged actor per step gives both the
        next action of the step just taken and the action of the following step; the first action of a rollout
        was drawn at the end of the previous one, before the update in between.

        :param env: The training environment
        :param callback: Callback that will be called at each step (and at the beginning and end of the rollout)
        :param rollout_buffer: Buffer to fill with rollouts
        :param n_rollout_steps: Number of experiences to collect per environment
        :return: True if function returned with at least `n_rollout_steps` collected,
            False if callback terminated rollout prematurely.
        """
        assert self._last_obs is not None, "No previous observation was provided"
        if self.policy.training:
            self.policy.set_training_mode(False)
        if self._pending_actions is None or self._last_obs is not self._rollout_obs:
            self._start_rollout(rollout_buffer)
        assert self._pending_actions is not None
        callback.on_rollout_start()

        for _ in range(n_rollout_steps):
            actions = self._pending_actions
            new_obs, rewards, dones, infos = env.step(self.policy.unscale_action(actions.cpu().numpy()))
            self.num_timesteps += env.num_envs

            terminated, truncated, terminal = split_episode_ends(dones, infos, self.device)
            all_truncated = terminal is not None and len(terminal.env_indices) == env.num_envs >= FEW_ENVS
            if all_truncated and not self._warned_synchronised_resets:
                self._warned_synchronised_resets = True
                warn_synchronised_resets()

            obs_tensor, obs_ok = observations_to_tensor(new_obs, self.device)
            self.policy.update_obs_normalizer(obs_tensor, obs_ok)
            with th.inference_mode():
                # Two draws of the averaged actor at s_{t+1}: the action of the next step, and the
                # "next action" a'_{t+1} of this transition for its value target
                next_step_actions, next_actions = self.actor_avg.sample(obs_tensor, 2)
                if terminal is not None:
                    next_actions[terminal.env_indices] = self.actor_avg.sample(terminal.observations, 1)[0]

            rollout_buffer.add(actions, rewards, terminated, truncated, obs_tensor, obs_ok, next_actions, terminal)
            self._last_obs = self._rollout_obs = new_obs  # type: ignore[assignment]
            self._last_episode_starts = dones
            self._pending_actions = next_step_actions
            if dones.any():  # episode statistics only come with finished episodes
                done_idx = np.flatnonzero(dones)
                self._update_info_buffer([infos[idx] for idx in done_idx], dones[done_idx])

            callback.update_locals(locals())
            if not callback.on_step():
                return False

        self.logger.record("rollout/nonfinite_transitions", rollout_buffer.n_nonfinite)
        callback.update_locals(locals())
        callback.on_rollout_end()
        return True

    def _critic_update(self, *minibatch: th.Tensor) -> th.Tensor:
        """One critic update on a minibatch given as ``samples_to_tensors`` does; returns its statistics."""
        data = samples_from_tensors(minibatch, self._obs_keys)
        return th.stack(self._critic_step(data, data.weights.sum().clamp_min(1.0)))

    def _actor_update(self, target_entropy: th.Tensor, *minibatch: th.Tensor) -> th.Tensor:
        """One actor and entropy-coefficient update, then the Polyak updates; returns the update's statistics."""
        data = samples_from_tensors(minibatch, self._obs_keys)
        stats = th.stack(self._actor_step(data, data.weights.sum().clamp_min(1.0), target_entropy))
        self._polyak_updates()
        return stats

    def _update_steps(self) -> tuple[Callable[..., th.Tensor], Callable[..., th.Tensor]]:
        """The critic and actor update functions: the eager ones, or their CUDA graphs (made at the first call)."""
        if not self._use_cuda_graphs:
            return self._critic_update, self._actor_update
        if self._graphed_updates is None:
            prepare_optimizers_for_capture(self._optimizers(), self.device)
            self._graphed_updates = (
                GraphedStep(self._critic_update, "critic update"),
                GraphedStep(self._actor_update, "actor update"),
            )
        return self._graphed_updates

    @property
    def _use_cuda_graphs(self) -> bool:
        return self.cuda_graphs and self.device.type == "cuda"

    def _optimizers(self) -> list[th.optim.Optimizer]:
        """The optimizers of the updates: actor, critics and, when alpha is learned, alpha's."""
        return [self.actor.optimizer, self.critic.optimizer, *([self.ent_coef_optimizer] if self.ent_coef_optimizer else [])]

    def _critic_step(self, data: CGACSamples, weight_sum: th.Tensor) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        # data: observations, actions, returns and weights, in the order of losses.critic_loss
        critic_loss, q_mean = self._critic_loss_fn(self.critic, *data, weight_sum, self.critic_loss, self._autocast_dtype)
        self.critic.optimizer.zero_grad(set_to_none=True)
        critic_loss.backward()
        grad_norm = th.nn.utils.clip_grad_norm_(self._critic_parameters, self.max_grad_norm)
        self.critic.optimizer.step()
        return critic_loss.detach(), q_mean, grad_norm

    def _actor_step(
        self, data: CGACSamples, weight_sum: th.Tensor, target_entropy: th.Tensor | float
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor, th.Tensor]:
        ent_coef = th.exp(self.log_ent_coef.detach()) if self.log_ent_coef is not None else self.ent_coef_tensor
        # Critic gradients are not needed for the actor loss (paper Eq. 7): skip their computation
        self.critic.set_q_requires_grad(False)
        if self.clip_actor_gradient_outliers:
            actor_loss, log_prob, self.gradient_ratio_average = outlier_clipped_actor_loss(
                self.actor, self.critic, data.observations, data.weights, weight_sum, ent_coef, self.gradient_ratio_average
            )
        else:
            actor_loss, log_prob = self._actor_loss_fn(
                self.actor, self.critic, data.observations, data.weights, weight_sum, ent_coef, self._autocast_dtype
            )
        if self.behaviour_kl_coef > 0:
            kl = behaviour_kl(self.actor, self.actor_avg, data.observations, data.weights, weight_sum)
            actor_loss = actor_loss + self.behaviour_kl_coef * kl
        self.actor.optimizer.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.critic.set_q_requires_grad(True)
        if self.actor_max_grad_norm is not None:
            grad_norm = th.nn.utils.clip_grad_norm_(self._actor_parameters, self.actor_max_grad_norm)
        else:
            # What torch.nn.utils.get_total_norm computes (torch >= 2.6 only; this package supports torch >= 2.4)
            grads = [param.grad for param in self._actor_parameters if param.grad is not None]
            grad_norm = th.linalg.vector_norm(th.stack(th._foreach_norm(grads)))
        self.actor.optimizer.step()

        ent_coef_loss = th.zeros_like(actor_loss)  # logged only when alpha is learned
        if self.ent_coef_optimizer is not None and self.log_ent_coef is not None:
            alpha_args = (log_prob, data.weights, weight_sum, target_entropy, self.ent_coef_monotone)
            ent_coef_loss = update_log_ent_coef(self.log_ent_coef, self.ent_coef_optimizer, *alpha_args)
        entropy = -(log_prob.detach() * data.weights).sum() / weight_sum
        return actor_loss.detach(), grad_norm, entropy, ent_coef_loss

    @th.no_grad()
    def _polyak_updates(self) -> None:
        # target <- (1 - tau) * target + tau * online, all parameters of a network in one foreach call
        th._foreach_lerp_(self._critic_target_parameters, self._critic_parameters, self._tau)
        th._foreach_lerp_(self._actor_avg_parameters, self._actor_parameters, self._policy_tau)
        if self.predict_tau is not None:
            th._foreach_lerp_(self._actor_predict_parameters, self._actor_parameters, self.predict_tau)

    def _update_learning_rates(self) -> None:
        progress = self._current_progress_remaining
        iterations = self._n_updates // (self._critic_updates_per_step * self.n_steps)
        actor_lr, critic_lr = (
            decayed_learning_rate(schedule(progress), self.final_learning_rate, iterations, self.lr_decay_iterations)
            for schedule in (self.lr_schedule, self.critic_lr_schedule)
        )
        set_learning_rate(self.actor.optimizer, actor_lr)
        set_learning_rate(self.critic.optimizer, critic_lr)
        self.logger.record("train/learning_rate", actor_lr)
        self.logger.record("train/critic_learning_rate", critic_lr)
        if self.ent_coef_optimizer is not None:
            lr = self.ent_coef_lr_schedule(progress) if self.ent_coef_lr_schedule else 10 * self.lr_schedule(progress)
            if self.decay_ent_coef_learning_rate and self.lr_schedule(progress) > 0:
                lr *= actor_lr / self.lr_schedule(progress)  # the decay's factor at this iteration
            set_learning_rate(self.ent_coef_optimizer, lr)
            self.logger.record("train/ent_coef_learning_rate", lr)

    def _sample_next_actions(self, obs: PyTorchObs) -> th.Tensor:
        return self.actor_avg.sample(obs, 1)[0]

    def train(self) -> None:
        """Value targets of the new steps, then critic, actor, entropy-coefficient and Polyak updates on minibatches."""
        sampler = self._sample_next_actions if self.refresh_target_values else None
        self.rollout_buffer.compute_returns(self.policy.target_q_value, next_action_sampler=sampler)
        if self.rollout_buffer.n_transitions < self._batch_size:
            return  # the window does not hold a minibatch yet
        self.policy.set_training_mode(True)
        self._update_learning_rates()
        target_entropy = -self.target_entropy_beta * float(get_action_dim(self.action_space))

        critic_update, actor_update = self._update_steps()
        target_entropy_tensor = th.full((), target_entropy, device=self.device)
        critic_stats, actor_stats = [], []
        for _ in range(self._critic_updates_per_step * self.n_steps):
            minibatch = samples_to_tensors(self.rollout_buffer.sample(self._batch_size))
            critic_stats.append(critic_update(*minibatch))
            self._n_updates += 1
            if self._n_updates % self.policy_delay == 0:
                actor_stats.append(actor_update(target_entropy_tensor, *minibatch))

        self.policy.set_training_mode(False)
        if not self.policy.parameters_finite(*([] if self.log_ent_coef is None else [self.log_ent_coef])):
            raise RuntimeError(
                f"CGAC: network parameters became NaN/Inf after {self._n_updates} critic updates; training cannot go on. "
                "Common causes: exploding rewards or observations (wrap the env in VecNormalize), a learning rate "
                "too high, or gradient clipping turned off (max_grad_norm)."
            )
        # One read of the statistics per iteration (no host-device sync inside the update loop)
        critic_names = ("critic_loss", "q_mean", "critic_grad_norm")
        stats = dict(zip(critic_names, th.stack(critic_stats).mean(dim=0).tolist(), strict=True))
        if actor_stats:
            names = ("actor_loss", "actor_grad_norm", "entropy", "ent_coef_loss")
            stats.update(zip(names, th.stack(actor_stats).mean(dim=0).tolist(), strict=True))
            if self.ent_coef_optimizer is None:
                del stats["ent_coef_loss"]
        stats.update(tau=self._tau, policy_tau=self._policy_tau, target_entropy=target_entropy)
        ent_coef = self.ent_coef_tensor if self.log_ent_coef is None else th.exp(self.log_ent_coef.detach())
        stats.update(beta=self.target_entropy_beta, ent_coef=ent_coef.item())
        if isinstance(self.actor.log_std, th.nn.Parameter):
            stats["std"] = th.exp(self.actor.log_std.detach()).mean().item()
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
        return super().learn(
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )

    def _excluded_save_params(self) -> list[str]:
        # Aliases into the policy (saved with it), and state rebuilt by _setup_model or at the next learn()
        excluded = ["actor", "actor_avg", "critic", "critic_target", "_pending_actions", "_rollout_obs"]
        excluded += ["_entropy_schedule_callback", "_warned_synchronised_resets", "_autocast_dtype", "_critic_loss_fn"]
        excluded += ["_actor_loss_fn", "_critic_parameters", "_actor_parameters"]
        excluded += ["_critic_target_parameters", "_actor_avg_parameters", "_actor_predict_parameters", "_graphed_updates"]
        excluded += ["_obs_keys"]
        return [*super()._excluded_save_params(), *excluded]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts = ["policy", "actor.optimizer", "critic.optimizer"]
        if self.ent_coef_optimizer is not None:
            return [*state_dicts, "ent_coef_optimizer"], ["gradient_ratio_average", "log_ent_coef"]
        return state_dicts, ["gradient_ratio_average", "ent_coef_tensor"]

    def get_parameters(self) -> dict[str, dict]:
        params = super().get_parameters()
        # CUDA graphs make the optimizers' learning rates tensors and their steps capturable: saved models hold the
        # plain form whatever the training used, so that they load on any device
        for name in ("actor.optimizer", "critic.optimizer", "ent_coef_optimizer"):
            for group in params.get(name, {}).get("param_groups", []):
                if isinstance(group["lr"], th.Tensor):  # set by prepare_optimizers_for_capture
                    release_param_group(group)
        return params

    def set_parameters(
        self, load_path_or_dict: str | TensorDict, exact_match: bool = True, device: th.device | str = "auto"
    ) -> None:
        # The networks load in place, the optimizers' states do not: the CUDA graphs of the updates read the old tensors,
        # so the loaded values are copied into those (a second capture of the same parameters' updates failed on CUDA)
        kept = keep_optimizer_tensors(self._optimizers()) if self._graphed_updates is not None else None
        super().set_parameters(load_path_or_dict, exact_match=exact_match, device=device)
        if kept is not None and not restore_optimizer_tensors(self._optimizers(), kept):
            release_optimizers_from_capture(self._optimizers())
            self._graphed_updates = None
