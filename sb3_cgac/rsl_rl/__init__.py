"""
rsl_rl's PPO (package ``rsl-rl-lib``: the PPO of Isaac Lab, mjlab and MuJoCo Playground's PyTorch path) on SB3
vector envs, as the reference baseline of ``python -m sb3_cgac.compare --runs cgac rsl_ppo`` (extra ``rsl_rl``).

``RslRlVecEnv`` gives any SB3 ``VecEnv`` rsl_rl's env interface; ``RslPPO`` drives rsl_rl's own ``PPO`` (its
actor-critic models, rollout storage, GAE and update) from an SB3-style ``learn()``, so that the zoo, callbacks,
the logger and ``evaluate_policy`` treat it like any SB3 algorithm. The training loop is that of rsl_rl's
``OnPolicyRunner.learn``; rsl_rl's runner itself also runs on ``RslRlVecEnv``.

The package: ``vec_env`` holds the env interface (``RslRlVecEnv``), ``ppo`` the algorithm (``RslPPO``) and its policy.
"""

from sb3_cgac.rsl_rl.ppo import RslActorCriticPolicy, RslPPO
from sb3_cgac.rsl_rl.vec_env import BOX_GROUP, RslRlVecEnv, observation_groups

__all__ = ["BOX_GROUP", "RslActorCriticPolicy", "RslPPO", "RslRlVecEnv", "observation_groups"]
