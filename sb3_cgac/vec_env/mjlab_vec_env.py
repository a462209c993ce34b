"""
mjlab's tasks (package ``mjlab``, MuJoCo Warp; extra ``mjlab``) as a torch-native vector env: observations, rewards
and flags stay torch tensors on the simulator's device, so that on a GPU the whole collection step stays there::

    from sb3_cgac.vec_env import TorchVecEnv
    from sb3_cgac.vec_env.mjlab_vec_env import MjlabVectorEnv

    env = TorchVecEnv(MjlabVectorEnv("Mjlab-Velocity-Flat-Unitree-Go1", num_envs=4096, device="cuda:0"),
                      random_first_episode=True)
    CGAC("MultiInputPolicy", env, policy_kwargs=dict(actor_keys=["actor"], critic_keys=["critic"])).learn(10_000_000)

The task runs with mjlab's ``auto_reset=False``: a step returns the last observation of the episodes that ended, which
becomes ``info["final_obs"]``, and the adapter then resets those envs (``reset(env_ids=...)``), as the same-step
autoreset of ``TorchVecEnv``'s contract does. mjlab's own autoreset (the default, and what rsl_rl's wrapper uses)
overwrites that observation with the reset one. A time-out is a truncation, a termination term a termination (both at
once: a termination); a finite-horizon task (``is_finite_horizon``) reports its time-outs as terminations. Each
observation group (``"actor"``, ``"critic"``, ...) is one key of a Dict observation: the asymmetric policy takes them as
its ``actor_keys`` and ``critic_keys``.
"""

from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from gymnasium.vector import AutoresetMode

from sb3_cgac.common.obs_rows import where_rows

try:
    import mjlab.tasks  # noqa: F401  (registers mjlab's tasks)
    from mjlab.envs import ManagerBasedRlEnv
    from mjlab.tasks.registry import list_tasks, load_env_cfg
except ImportError as error:  # pragma: no cover - the extra is missing
    raise ImportError("sb3_cgac.vec_env.mjlab_vec_env needs mjlab: pip install 'sb3_cgac[mjlab]'.") from error


class MjlabVectorEnv(gym.vector.VectorEnv):
    """
    ``num_envs`` copies of an mjlab task with torch tensors in and out (the torch-native contract of ``TorchVecEnv``:
    same-step autoreset, ``info["final_obs"]``, partial resets with ``reset(options={"reset_mask": mask})``).

    :param task_id: An mjlab task, e.g. ``"Mjlab-Velocity-Flat-Unitree-Go1"`` (``mjlab.tasks.registry.list_tasks()``)
    :param num_envs: Number of parallel envs
    :param device: Device of the simulation (``"cuda:0"``; ``"cpu"`` runs MuJoCo Warp's CPU backend, for tests)
    :param clip_actions: The bounds ``[-clip_actions, clip_actions]`` of the action space (mjlab's actions are
        unbounded; CGAC squashes its actions into the space's bounds), in units of the task's action scale
    :param play: Use the task's "play" configuration (evaluation) instead of its training one
    :param episode_length_s: Time limit of the episodes in seconds (None: the task's)
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(
        self,
        task_id: str,
        num_envs: int,
        device: str = "cuda:0",
        clip_actions: float = 1.0,
        play: bool = False,
        episode_length_s: float | None = None,
    ):
        if task_id not in list_tasks():
            raise ValueError(f"mjlab has no task {task_id!r}; its tasks: {list_tasks()}.")
        cfg = load_env_cfg(task_id, play=play)
        cfg.scene.num_envs = num_envs
        cfg.auto_reset = False  # the adapter resets, after keeping the last observation
        if episode_length_s is not None:
            cfg.episode_length_s = episode_length_s
        self.env = ManagerBasedRlEnv(cfg, device=device)
        self.num_envs = num_envs
        self.device = th.device(self.env.device)
        self.max_episode_steps = int(self.env.max_episode_length)
        self.finite_horizon = bool(getattr(cfg, "is_finite_horizon", False))
        self.clip_actions = clip_actions
        obs, _ = self.env.reset()
        for name, value in obs.items():
            if not isinstance(value, th.Tensor) or value.ndim != 2:
                raise ValueError(
                    f"MjlabVectorEnv: the observation group {name!r} of {task_id} is not one flat tensor per env; set "
                    "its concatenate_terms=True (mjlab's default)."
                )
        self.single_observation_space = spaces.Dict(
            {name: spaces.Box(-np.inf, np.inf, (value.shape[1],), np.float32) for name, value in obs.items()}
        )
        action_dim = int(self.env.action_manager.total_action_dim)
        self.single_action_space = spaces.Box(-clip_actions, clip_actions, (action_dim,), np.float32)
        self.reward_terms = list(self.env.reward_manager.active_terms)
        self._reward_keys = [f"reward_{term}" for term in self.reward_terms]
        self._no_reward_terms = th.zeros(num_envs, device=self.device)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        if options and "reset_mask" in options:
            mask = th.as_tensor(options["reset_mask"], device=self.device).bool()
            obs = {name: value.clone() for name, value in self.env.get_observations().items()}
            fresh, _ = self.env.reset(env_ids=mask.nonzero().squeeze(-1))
            # A partial reset recomputes every env's observation (new noise draws): only the reset rows change
            return where_rows(mask, dict(fresh), dict(obs)), {}
        obs, _ = self.env.reset(seed=seed)
        return dict(obs), {}

    def step(self, actions: Any) -> tuple[Any, th.Tensor, th.Tensor, th.Tensor, dict[str, Any]]:
        actions = th.as_tensor(actions, dtype=th.float32, device=self.device).clamp(-self.clip_actions, self.clip_actions)
        obs, rewards, terminated, time_outs, _ = self.env.step(actions)
        obs = {name: value.clone() for name, value in obs.items()}  # the reset below recomputes mjlab's buffers
        if self.finite_horizon:
            terminated, time_outs = terminated | time_outs, th.zeros_like(time_outs)
        truncated = time_outs & ~terminated
        done = terminated | truncated
        info: dict[str, Any] = {"final_obs": obs, **dict.fromkeys(self._reward_keys, self._no_reward_terms)}
        done_ids = done.nonzero().squeeze(-1)
        if done_ids.numel() > 0:  # mjlab's own step reads the same count from the device
            fresh, _ = self.env.reset(env_ids=done_ids)
            obs = where_rows(done, dict(fresh), obs)
            # The reset's log: each term's episode sum averaged over the reset envs, per second of the time limit
            log, seconds = self.env.extras["log"], self.env.max_episode_length_s
            for key, term in zip(self._reward_keys, self.reward_terms, strict=True):
                info[key] = th.where(done, log[f"Episode_Reward/{term}"] * seconds, self._no_reward_terms)
        return obs, rewards.float(), terminated.bool(), truncated.bool(), info

    def close(self, **kwargs: Any) -> None:
        self.env.close()
