"""
The collection half of CGAC (as SB3 keeps ``collect_rollouts`` in ``OnPolicyAlgorithm`` and the updates in PPO):
:class:`WindowOnPolicyAlgorithm` steps the envs with the averaged actor into a rolling window that stores, for each
transition, the "next action" its Q-GAE target needs; ``CGAC`` adds the updates.
"""

import warnings
from typing import Any, TypeVar

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
from stable_baselines3.common.vec_env import VecEnv

from sb3_cgac.buffers import CGACRolloutBuffer
from sb3_cgac.collection import EnvStep, tensor_env_step, tensor_observations, vec_env_observations, vec_env_step
from sb3_cgac.common.distributed import DataParallel
from sb3_cgac.hyperparameters import FEW_ENVS
from sb3_cgac.policies import CGACPolicy
from sb3_cgac.return_scale import ReturnScale
from sb3_cgac.vec_env.episodes import episode_metrics
from sb3_cgac.vec_env.torch_vec_env import TorchVecEnv

SelfWindowAlgorithm = TypeVar("SelfWindowAlgorithm", bound="WindowOnPolicyAlgorithm")


def warn_synchronised_resets(infos: list[dict[str, Any]], n_envs: int) -> bool:
    """
    Warn when all envs reached their time limit at the same step (CGAC's rollout collection warns once per model).

    :param infos: The infos of a step at which every env's episode ended
    :param n_envs: Number of envs; fewer than ``FEW_ENVS`` are expected to reset together
    :return: Whether it warned
    """
    if n_envs < FEW_ENVS or not all(info.get("TimeLimit.truncated", False) for info in infos):
        return False
    warnings.warn(
        "CGAC: all envs reached their time limit at the same step, so for the next steps the window holds "
        "only initial states and the critic forgets the rest (paper Sec. 4.2). Spread the resets: build the "
        "envs with sb3_cgac.vec_env.make_vec_env (it cuts first episodes at random lengths by default), or "
        "pass wrapper_class=sb3_cgac.vec_env.wrappers.RandomFirstEpisodeLength to SB3's make_vec_env.",
        UserWarning,
        stacklevel=3,
    )
    return True


class WindowOnPolicyAlgorithm(OnPolicyAlgorithm):
    """
    An on-policy algorithm whose rollouts go into a window of the last steps of every env (``CGACRolloutBuffer``),
    collected with the policy's averaged actor. Each transition also stores the action the averaged actor draws at its
    next observation (the real terminal one at a time limit), and the policy's in-policy observation statistics follow
    every observation. A ``TorchVecEnv`` is stepped with device tensors, without host syncs.
    """

    policy: CGACPolicy  # type: ignore[assignment]
    rollout_buffer: CGACRolloutBuffer  # type: ignore[assignment]
    # Collection state: actions already sampled for `_last_obs`, and the `_last_obs` the window ends with
    _pending_actions: th.Tensor | None = None
    _rollout_obs: Any = None
    _warned_synchronised_resets = False
    # Data-parallel training (sb3_cgac.common.distributed), started by learn() under torchrun
    _parallel: DataParallel | None = None
    # The scaling of the rewards the window stores (None: as the env gives them)
    return_scale: ReturnScale | None = None

    def _start_rollout(self, buffer: CGACRolloutBuffer, tensor_env: TorchVecEnv | None) -> None:
        # The window's trajectories end where `_last_obs` does not continue them (first call, env reset,
        # set_env, load): start a new window from `_last_obs`.
        if tensor_env is not None:
            obs, ok = tensor_observations(tensor_env.last_observations, self.device)
        else:
            obs, ok = vec_env_observations(self._last_obs, self.device)  # type: ignore[arg-type]
        buffer.reset()
        buffer.set_current_obs(obs, ok)
        if self.return_scale is not None:  # the envs' running returns restart with the window
            self.return_scale.reset_returns()
        self.policy.update_obs_normalizer(obs, ok, self._parallel.sum if self._parallel else None)
        with th.inference_mode():
            self._pending_actions = self.policy.actor_avg.sample(obs, 1)[0]
        self._rollout_obs = self._last_obs

    def _step_env(self, env: VecEnv, actions: th.Tensor) -> tuple[Any, EnvStep, tuple[Any, Any, Any]]:
        """
        One step of every env; returns what ``_last_obs`` becomes, the step as the window stores it (tensors on the
        policy's device) and the rewards, dones and infos as the env gave them (the callbacks' locals, as in SB3).
        """
        if isinstance(env, TorchVecEnv):  # tensors on the device throughout, no host sync
            tensor_step = env.step_tensors(self.policy.unscale_action_tensor(actions))
            step = tensor_env_step(tensor_step, self.device)
            return tensor_step.observations, step, (step.rewards, step.dones, step.infos)
        new_obs, rewards, dones, infos = env.step(self.policy.unscale_action(actions.cpu().numpy()))
        step = vec_env_step(new_obs, rewards, dones, infos, self.device)  # the only conversion from NumPy
        if not self._warned_synchronised_resets and dones.all():  # once per model
            self._warned_synchronised_resets = warn_synchronised_resets(infos, env.num_envs)
        if dones.any():  # episode statistics only come with finished episodes
            done_idx = np.flatnonzero(dones)
            self._update_info_buffer([infos[idx] for idx in done_idx], dones[done_idx])
        self._last_episode_starts = dones
        return new_obs, step, (rewards, dones, infos)

    def collect_rollouts(  # type: ignore[override]
        self,
        env: VecEnv,
        callback: BaseCallback,
        rollout_buffer: CGACRolloutBuffer,
        n_rollout_steps: int,
    ) -> bool:
        """
        Collect ``n_rollout_steps`` steps of every env into the window, with their next actions.

        :return: True if ``n_rollout_steps`` were collected, False if a callback stopped the rollout
        """
        assert self._last_obs is not None, "No previous observation was provided"
        if self.policy.training:
            self.policy.set_training_mode(False)
        tensor_env = env if isinstance(env, TorchVecEnv) else None
        if self._pending_actions is None or self._last_obs is not self._rollout_obs:
            self._start_rollout(rollout_buffer, tensor_env)
        assert self._pending_actions is not None
        callback.on_rollout_start()

        for _ in range(n_rollout_steps):
            actions = self._pending_actions
            new_obs, step, (rewards, dones, infos) = self._step_env(env, actions)  # SB3's names, for the callbacks' locals
            self.num_timesteps += env.num_envs
            self.policy.update_obs_normalizer(step.observations, step.obs_ok, self._parallel.sum if self._parallel else None)
            with th.inference_mode():
                # The action of the next step at s_{t+1}, and the "next action" a'_{t+1} of this transition for its
                # value target (at the terminal observation of a truncated episode)
                next_step_actions = self.policy.actor_avg.sample(step.observations, 1)[0]
                next_actions = self.policy.actor_avg.sample(step.bootstrap_observations(), 1)[0]

            if self.return_scale is not None:  # the window's rewards only: the callbacks' locals keep the env's
                reductions = (self._parallel.sum, self._parallel.max) if self._parallel else (None, None)
                step = step._replace(rewards=self.return_scale.scale_rewards(step.rewards, step.dones, *reductions))
            rollout_buffer.add(actions, step, next_actions)
            self._last_obs = self._rollout_obs = new_obs
            self._pending_actions = next_step_actions

            callback.update_locals(locals())
            keep_going = callback.on_step()
            if self._parallel is not None:  # a callback of one rank (rank 0's evaluation) stops every rank
                keep_going = self._parallel.all_agree(keep_going)
            if not keep_going:
                return False

        if tensor_env is not None:  # the finished episodes, copied to the host without waiting (on a GPU, a rollout late)
            self.ep_info_buffer.extend(tensor_env.pop_episodes(wait=False))  # type: ignore[union-attr]
        if self._parallel is not None:  # one set of VecNormalize statistics for every rank
            self._parallel.sync_vec_normalize(self.get_vec_normalize_env())
        callback.update_locals(locals())
        callback.on_rollout_end()
        return True

    def learn(self: SelfWindowAlgorithm, *args: Any, **kwargs: Any) -> SelfWindowAlgorithm:
        super().learn(*args, **kwargs)
        env = self.get_env()
        if isinstance(env, TorchVecEnv):  # the episodes whose copy to the host was still under way
            self.ep_info_buffer.extend(env.pop_episodes())  # type: ignore[union-attr]
        return self

    def dump_logs(self, iteration: int = 0) -> None:
        # The adapters' episode statistics (reward components, task metrics) beside rollout/ep_rew_mean
        for key, value in episode_metrics(self.ep_info_buffer or ()).items():
            self.logger.record(f"rollout/ep_{key}_mean", value)
        # Read when the logs are written (a torch-native env counts them on the device)
        self.logger.record("rollout/nonfinite_transitions", self.rollout_buffer.n_nonfinite)
        super().dump_logs(iteration)

    def _excluded_save_params(self) -> list[str]:
        # Collection state, rebuilt at the next learn() (a torch-native env's observations may be on a GPU)
        excluded = ["_pending_actions", "_rollout_obs", "_warned_synchronised_resets", "_parallel", "_last_obs"]
        return [*super()._excluded_save_params(), *excluded]
