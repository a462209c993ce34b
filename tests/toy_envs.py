"""The tests' toy envs: a point moved by the actions, observed as a Box or through a Dict, with a fixed time limit."""

import gymnasium as gym
import numpy as np
from gymnasium import spaces


class ToyEnv(gym.Env):
    """A state of ``state_dim`` numbers drawn in [-1, 1] at each reset; subclasses define ``_obs`` and ``step``."""

    state_dim = 2
    action_space = spaces.Box(-1, 1, (2,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.state = self.np_random.uniform(-1, 1, self.state_dim).astype(np.float32)
        self.steps = 0
        return self._obs(), {}

    def _obs(self):
        raise NotImplementedError


class PrivilegedEnv(ToyEnv):
    """The robot senses a noisy position (``state``); the simulator knows it exactly (``privileged_state``)."""

    observation_space = spaces.Dict(
        {"state": spaces.Box(-10, 10, (2,), np.float32), "privileged_state": spaces.Box(-10, 10, (3,), np.float32)}
    )

    def _obs(self):
        noise = self.np_random.normal(0, 0.1, 2).astype(np.float32)
        return {"state": self.state + noise, "privileged_state": np.append(self.state, self.steps / 20).astype(np.float32)}

    def step(self, action):
        self.state = np.clip(self.state + 0.1 * action, -10, 10).astype(np.float32)
        self.steps += 1
        return self._obs(), -float(np.sum(self.state**2)), False, self.steps >= 20, {}


class ReachEnv(ToyEnv):
    """A point pushed by the actions: terminated when it leaves the square, truncated after 25 steps."""

    def __init__(self, dict_obs: bool = False):
        box = spaces.Box(-10, 10, (2,), np.float32)
        self.dict_obs = dict_obs
        privileged = spaces.Box(-10, 10, (3,), np.float32)
        self.observation_space = spaces.Dict({"state": box, "privileged_state": privileged}) if dict_obs else box

    def _obs(self):
        if not self.dict_obs:
            return self.state.copy()
        privileged = np.append(self.state, self.steps / 25).astype(np.float32)
        return {"state": self.state.copy(), "privileged_state": privileged}

    def step(self, action):
        self.state = (self.state + 0.3 * np.asarray(action, np.float32)).astype(np.float32)
        self.steps += 1
        terminated = bool(np.abs(self.state).max() > 1.5)
        reward = -float(np.sum(self.state**2))
        # Reward components, reported at every step (not at a reset): summed into the episode statistics
        info = {"reward_distance": reward, "reward_steps": float(self.steps)}
        return self._obs(), reward, terminated, self.steps >= 25, info


class DictObsEnv(ToyEnv):
    """Dict observation: a position vector and a velocity; reward for driving both to zero."""

    state_dim = 3
    observation_space = spaces.Dict(
        {"position": spaces.Box(-10, 10, (2,), np.float32), "velocity": spaces.Box(-10, 10, (1,), np.float32)}
    )

    def _obs(self):
        return {"position": self.state[:2].copy(), "velocity": self.state[2:].copy()}

    def step(self, action):
        self.state[:2] = np.clip(self.state[:2] + 0.1 * action, -10, 10)
        self.state[2] = np.clip(0.9 * self.state[2], -10, 10)
        self.steps += 1
        reward = -float(np.sum(self.state**2))
        return self._obs(), reward, False, self.steps >= 20, {}
