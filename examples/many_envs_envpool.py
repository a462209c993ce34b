"""
CGAC on HalfCheetah-v5 with many parallel envs stepped by envpool in C++ threads (``pip install -e ".[envpool]"``).

    python examples/many_envs_envpool.py [--n-envs 128] [--timesteps 1000000]

The settings are the HalfCheetah-v5 entry of ``hyperparams/cgac.yml``. Observations are normalised with SB3's
``VecNormalize``, as the paper does (running mean and std); the rewards are left as they are.
"""

import argparse

from sb3_cgac.threads import configure_thread_spin

# First, before anything loads torch: torch's idle threads then do not spin on the cores envpool steps on
configure_thread_spin()

from stable_baselines3.common.evaluation import evaluate_policy  # noqa: E402
from stable_baselines3.common.vec_env import VecNormalize  # noqa: E402

from sb3_cgac import CGAC  # noqa: E402
from sb3_cgac.callbacks import RewardEntropySchedule  # noqa: E402
from sb3_cgac.vec_env import EnvPoolVecEnv  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-envs", type=int, default=128)
    parser.add_argument("--timesteps", type=int, default=1_000_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    env = VecNormalize(EnvPoolVecEnv("HalfCheetah-v5", num_envs=args.n_envs, seed=args.seed), norm_reward=False)
    # On a CPU the defaults are the entry's update cost and averaging (batch 512, 4 critic updates per step)
    model = CGAC(
        "MlpPolicy",
        env,
        # The actor starts from near-zero mean actions: with the paper's init one seed in three stayed stuck for minutes
        policy_kwargs=dict(mean_init_scale=0.01),
        seed=args.seed,
        verbose=1,
    )
    # The paper's Eq. 13: the target entropy falls (beta rises) as the per-step reward improves
    schedule = RewardEntropySchedule(beta_init=0.2, beta_final=3.5, init_expected_reward=0.0, peak_expected_reward=8.0)
    model.learn(args.timesteps, callback=schedule, log_interval=100, progress_bar=True)

    # Evaluate on a separate pool with the training statistics of the observations, frozen
    eval_env = VecNormalize(EnvPoolVecEnv("HalfCheetah-v5", num_envs=5, seed=args.seed + 1000), norm_reward=False)
    eval_env.obs_rms, eval_env.training = env.obs_rms, False
    mean_return, std_return = evaluate_policy(model, eval_env, n_eval_episodes=10, deterministic=True)
    print(f"Mean evaluation return after {model.num_timesteps} steps: {mean_return:.0f} +/- {std_return:.0f}")


if __name__ == "__main__":
    main()
