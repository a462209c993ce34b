"""
Quickstart: train CGAC on Pendulum-v1 with 64 parallel envs, evaluate it, save and reload it.

    python examples/quickstart.py [--timesteps 200000]

A minute or two on 2 CPU cores. A random policy scores about -1200; after 200k steps most seeds end at -260 or above
(10 of seeds 0-11, between -147 and -257), some are still learning (seed 0: -835, seed 3: -354).
"""

import argparse

from stable_baselines3.common.evaluation import evaluate_policy

from sb3_cgac import CGAC
from sb3_cgac.vec_env import make_vec_env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--timesteps", type=int, default=200_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--save-path", default="cgac_pendulum")
    args = parser.parse_args()

    # CGAC wants many parallel envs: it learns on-policy from a short window of all of them. sb3_cgac's make_vec_env
    # cuts each env's first episode at a random length, so that the envs do not all reset at the same steps (the
    # window would then hold nothing but initial states)
    env = make_vec_env("Pendulum-v1", n_envs=64, seed=args.seed)
    # The defaults (on a CPU: batch 512, 4 critic updates per step, Polyak rates 0.02 and 0.05) with the zoo entry's
    # shorter horizon and small networks
    model = CGAC(
        "MlpPolicy",
        env,
        gamma=0.98,  # shorter horizon than the default 0.99, as rl-zoo uses for Pendulum
        policy_kwargs=dict(net_arch=[64, 64]),
        seed=args.seed,
        verbose=1,
    )
    model.learn(args.timesteps, log_interval=500, progress_bar=True)

    eval_env = make_vec_env("Pendulum-v1", n_envs=10, seed=args.seed + 1000)
    mean_return, std_return = evaluate_policy(model, eval_env, n_eval_episodes=20, deterministic=True)
    print(f"Mean evaluation return after {model.num_timesteps} steps: {mean_return:.1f} +/- {std_return:.1f}")

    model.save(args.save_path)
    reloaded = CGAC.load(args.save_path, env=eval_env)
    mean_return, _ = evaluate_policy(reloaded, eval_env, n_eval_episodes=20, deterministic=True)
    print(f"Reloaded from {args.save_path}.zip: mean return {mean_return:.1f}")


if __name__ == "__main__":
    main()
