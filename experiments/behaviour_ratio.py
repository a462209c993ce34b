"""
How far CGAC's trained actor is from the averaged actor that collects its window: after training, the likelihood
ratio ``pi(a|s) / mu(a|s)`` of each kept step's actions, where ``mu`` is the averaged actor as it was when it took
them (its log-likelihoods recorded at the end of each rollout, before the updates change it) and ``pi`` the trained
actor now, by the step's age in iterations: the median ``|log ratio|`` and the share outside PPO's clip range
[0.8, 1.2]. A likelihood-ratio term on the window (PPO's clipped surrogate) passes gradients only inside that range::

    python experiments/behaviour_ratio.py --env HalfCheetah-v5 --n-envs 64 --steps 25600
"""

import argparse

import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.distributions import SquashedDiagGaussianDistribution

from sb3_cgac import CGAC
from sb3_cgac.policies import Actor
from sb3_cgac.vec_env import make_vec_env

CLIP_RANGE = 0.2  # PPO's default
# Candidate 1 of the critic screen (docs/tuning.md): the critics beside which a likelihood-ratio term was tried
CRITIC = dict(net_arch=dict(pi=[256, 256], qf=[512, 256]), critic_layer_norm=True, n_bins=101, actor_q_reduction="mean")


def log_prob(actor: Actor, obs: th.Tensor, actions: th.Tensor) -> th.Tensor:
    with th.no_grad():
        mean_actions, log_std = actor.get_action_dist_params(obs)
        distribution = SquashedDiagGaussianDistribution(actions.shape[-1]).proba_distribution(mean_actions, log_std)
        return distribution.log_prob(actions)


class RecordBehaviour(BaseCallback):
    """At each rollout's end, the newest step of the window and the averaged actor's log-likelihood of its actions."""

    def __init__(self) -> None:
        super().__init__()
        self.steps: list[tuple[th.Tensor, th.Tensor, th.Tensor]] = []

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        model = self.model
        assert isinstance(model, CGAC)
        buffer = model.rollout_buffer
        slot = (buffer.pos - 1) % buffer.buffer_window
        assert isinstance(buffer.observations, th.Tensor)  # a Box observation space: the MuJoCo tasks it measures
        obs, actions = buffer.observations[slot].clone(), buffer.actions[slot].clone()
        self.steps.append((obs, actions, log_prob(model.actor_avg, obs, actions)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="HalfCheetah-v5")
    parser.add_argument("--n-envs", type=int, default=64)
    parser.add_argument("--steps", type=int, default=25_600)
    parser.add_argument("--window", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    th.set_num_threads(1)
    env = make_vec_env(args.env, n_envs=args.n_envs, seed=args.seed)
    model = CGAC("MlpPolicy", env, buffer_window=args.window, policy_kwargs=CRITIC, seed=args.seed)
    recorder = RecordBehaviour()
    model.learn(args.steps, callback=recorder)
    print(f"{args.env}, {args.n_envs} envs, {model.num_timesteps} steps, window {args.window}, seed {args.seed}")
    print("age (iterations) | median |log ratio| trained/behaviour | outside [0.8, 1.2] | averaged now/behaviour outside")
    # Ages of steps the window still holds
    for age in sorted(age for age in {0, 1, 3, 10, 30, 100, args.window - 1} if age < min(args.window, len(recorder.steps))):
        obs, actions, behaviour = recorder.steps[-1 - age]
        trained = log_prob(model.actor, obs, actions) - behaviour
        averaged = log_prob(model.actor_avg, obs, actions) - behaviour
        outside = ((trained.exp() - 1).abs() > CLIP_RANGE).float().mean()
        averaged_outside = ((averaged.exp() - 1).abs() > CLIP_RANGE).float().mean()
        print(f"{age:3d} | {trained.abs().median():.2f} | {outside:.2f} | {averaged_outside:.2f}")


if __name__ == "__main__":
    main()
