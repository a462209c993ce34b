"""rsl_rl's env interface over an SB3 VecEnv (``RslRlVecEnv``) and observations as rsl_rl's observation groups."""

from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnv

from sb3_cgac.vec_env import TorchVecEnv, episode_metrics

try:
    from rsl_rl.env import VecEnv as RslVecEnvBase
    from tensordict import TensorDict
except ImportError as error:  # pragma: no cover - the extra is missing
    raise ImportError("sb3_cgac.rsl_rl needs rsl_rl: pip install 'sb3_cgac[rsl_rl]' (or pip install rsl-rl-lib).") from error

# The observation group of a Box observation (rsl_rl's name for the actor's observations)
BOX_GROUP = "policy"


def observation_groups(
    obs: np.ndarray | dict[str, np.ndarray] | th.Tensor | dict[str, th.Tensor], device: th.device
) -> TensorDict:
    """
    A batch of observations (arrays or tensors, a Box's or a Dict's) as rsl_rl's TensorDict of observation groups
    (a Box observation: ``policy``).
    """
    groups = obs if isinstance(obs, dict) else {BOX_GROUP: obs}
    tensors = {key: th.as_tensor(value, dtype=th.float32, device=device) for key, value in groups.items()}
    return TensorDict(tensors, batch_size=[len(next(iter(tensors.values())))], device=device)


class RslRlVecEnv(RslVecEnvBase):
    """
    rsl_rl's ``VecEnv`` interface over a Stable-Baselines3 ``VecEnv``: observations as a TensorDict of groups (the
    keys of a Dict observation, ``policy`` for a Box), ``extras["time_outs"]`` from SB3's ``TimeLimit.truncated``
    (rsl_rl then bootstraps those rewards with the value of the step's observation), and the Monitor episode
    statistics in ``extras["log"]``. Actions are clipped to the action space, as SB3's algorithms do. A
    ``TorchVecEnv`` (GPU simulators) is stepped with tensors, without host copies; its episodes are read by ``RslPPO``
    once per rollout (``extras["log"]`` stays empty).

    :param venv: The SB3 vector env (e.g. from ``sb3_cgac.vec_env.make_vec_env``, with or without ``VecNormalize``)
    :param device: Device of the tensors
    """

    def __init__(self, venv: VecEnv, device: th.device | str = "cpu"):
        if not isinstance(venv.action_space, spaces.Box):
            raise ValueError(f"RslRlVecEnv: rsl_rl's PPO needs a Box action space, got {venv.action_space}.")
        self.venv = venv
        self.num_envs = venv.num_envs
        self.num_actions = int(np.prod(venv.action_space.shape))
        self.device = th.device(device)
        self.cfg: dict = {}
        max_steps = getattr(venv.unwrapped, "max_episode_steps", None)
        self.max_episode_length = int(max_steps()) if callable(max_steps) else 0
        self.episode_length_buf = th.zeros(self.num_envs, dtype=th.long, device=self.device)
        self.last_infos: list[dict[str, Any]] = []
        self.last_obs: np.ndarray | dict[str, np.ndarray] | None = None  # as the SB3 env returned them
        self._obs: TensorDict | None = None

    def set_observations(self, obs: np.ndarray | dict[str, np.ndarray]) -> None:
        """Take the observations of a reset done outside (SB3's ``learn()`` resets the env itself)."""
        self.last_obs = obs
        self._obs = observation_groups(obs, self.device)
        self.episode_length_buf.zero_()

    def reset(self) -> TensorDict:
        self.set_observations(self.venv.reset())  # type: ignore[arg-type]
        assert self._obs is not None
        return self._obs

    def get_observations(self) -> TensorDict:
        return self._obs if self._obs is not None else self.reset()

    def step(self, actions: th.Tensor) -> tuple[TensorDict, th.Tensor, th.Tensor, dict]:
        space = self.venv.action_space
        assert isinstance(space, spaces.Box)
        if isinstance(self.venv, TorchVecEnv):
            return self._step_tensors(actions, space)
        clipped = np.clip(actions.detach().cpu().numpy().reshape(-1, *space.shape), space.low, space.high)
        obs, rewards, dones, infos = self.venv.step(clipped)
        self.last_infos, self.last_obs = infos, obs  # type: ignore[assignment]
        self._obs = observation_groups(obs, self.device)  # type: ignore[arg-type]
        done = th.as_tensor(dones, device=self.device)
        self.episode_length_buf += 1
        self.episode_length_buf[done] = 0
        # Only the finished envs carry episode ends: no loop over every env at every step
        finished = np.flatnonzero(dones)
        time_outs = th.zeros(self.num_envs, dtype=th.bool, device=self.device)
        time_outs[[int(idx) for idx in finished if infos[idx].get("TimeLimit.truncated", False)]] = True
        episodes = [infos[idx]["episode"] for idx in finished if "episode" in infos[idx]]
        log = {f"/episode_{key}": value for key, value in episode_metrics(episodes).items()}
        if episodes:
            log["/episode_return"] = float(np.mean([episode["r"] for episode in episodes]))
        extras = {"time_outs": time_outs, "log": log}
        rewards_tensor = th.as_tensor(rewards, dtype=th.float32, device=self.device)
        return self._obs, rewards_tensor, done.long(), extras

    def _step_tensors(self, actions: th.Tensor, space: spaces.Box) -> tuple[TensorDict, th.Tensor, th.Tensor, dict]:
        assert isinstance(self.venv, TorchVecEnv)
        low, high = (th.as_tensor(bound, device=actions.device) for bound in (space.low, space.high))
        step = self.venv.step_tensors(th.clamp(actions.reshape(-1, *space.shape), low, high))
        self.last_obs = step.observations  # type: ignore[assignment]
        self._obs = observation_groups(step.observations, self.device)
        done = (step.terminated | step.truncated).to(self.device)
        self.episode_length_buf += 1
        self.episode_length_buf.masked_fill_(done, 0)
        extras = {"time_outs": step.truncated.to(self.device), "log": {}}
        return self._obs, step.rewards.to(self.device, th.float32), done.long(), extras
