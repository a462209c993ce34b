"""
How a trained policy of any entry uses each action dimension: trains the entry of ``hyperparams/<run>.yml`` (``cgac``,
``ppo_parallel``, ``rsl_ppo``...) for ``--steps`` env steps as ``python -m sb3_cgac.compare`` builds it, then acts
deterministically for one episode in each env of an evaluation env and prints the mean return and, per dimension, the
mean action (clipped to [-1, 1] after scaling to the action space's bounds), its mean magnitude and the share of steps
beyond 0.99 in magnitude. A steady push shows as a mean near its magnitude, bang-bang control as a mean near 0 with
a magnitude near 1. ``--gains`` then acts with the deterministic actions multiplied by each gain (in [-1, 1], clipped
there): whether larger actions than the policy's own would score more (a gain of 100 is its bang-bang version)::

    python experiments/policy_actions.py --env MuJoCoPlayground/PandaPickCube-v1 --run ppo_parallel --steps 1700000
"""

import argparse
import time
from typing import Any

from sb3_cgac.threads import configure_thread_spin

configure_thread_spin()

import numpy as np  # noqa: E402
import torch as th  # noqa: E402
from stable_baselines3.common.vec_env import VecEnv, sync_envs_normalization  # noqa: E402

from sb3_cgac.zoo import HYPERPARAMS_DIR, algorithm_of, build_model  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="MuJoCoPlayground/PandaPickCube-v1")
    parser.add_argument("--run", default="cgac", help="a hyperparameter file of hyperparams/ (or of --conf-dir)")
    parser.add_argument("--conf-dir", default=str(HYPERPARAMS_DIR))
    parser.add_argument("--backend", default="envpool")
    parser.add_argument("--steps", type=int, default=1_000_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-envs", type=int, default=64, help="evaluation envs, one episode each")
    parser.add_argument("--gains", type=float, nargs="*", default=[], help="gains of the actions to evaluate, e.g. 1 2 4 100")
    parser.add_argument("--log-folder", default="/tmp/policy_actions", help="where the zoo writes the run's config")
    args = parser.parse_args()

    th.set_num_threads(1)  # one core for the updates, the other for envpool's thread
    model, manager = build_model(
        algorithm_of(args.run),
        args.env,
        seed=args.seed,
        backend=args.backend,
        backend_kwargs=dict(num_threads=1) if args.backend == "envpool" else None,
        log_folder=args.log_folder,
        conf_file=f"{args.conf_dir}/{args.run}.yml",
    )
    start = time.perf_counter()
    model.learn(args.steps, callback=manager.callbacks)
    print(f"{args.run}, seed {args.seed}: {model.num_timesteps} steps in {time.perf_counter() - start:.0f} s")

    env = manager.create_envs(args.eval_envs, eval_env=True, no_log=True)
    train_env = model.get_env()
    if model.get_vec_normalize_env() is not None and train_env is not None:
        sync_envs_normalization(train_env, env)
    returns, taken = episodes(model, env, gain=1.0)
    print(f"Deterministic policy, {env.num_envs} evaluation episodes: return {returns.mean():.4g}, {len(taken)} steps")
    print("\n| dimension | mean action | mean magnitude | magnitude > 0.99 |\n| --- | --- | --- | --- |")
    for dimension in range(taken.shape[1]):
        values = taken[:, dimension]
        print(f"| {dimension} | {values.mean():+.2f} | {np.abs(values).mean():.2f} | {(np.abs(values) > 0.99).mean():.2f} |")
    if args.gains:
        print("\n| gain | return (standard error) | magnitude > 0.99 |\n| --- | --- | --- |")
        for gain in args.gains:
            returns, taken = episodes(model, env, gain)
            standard_error = returns.std(ddof=1) / np.sqrt(len(returns))
            print(f"| {gain:g} | {returns.mean():.4g} ({standard_error:.2g}) | {(np.abs(taken) > 0.99).mean():.2f} |")
    env.close()


def episodes(model: Any, env: VecEnv, gain: float) -> tuple[np.ndarray, np.ndarray]:
    """
    One deterministic episode in each env, with the actions (in [-1, 1] of the action space's bounds) multiplied by
    ``gain`` and clipped there: the episodes' returns and the actions taken, in [-1, 1].
    """
    low, high = env.action_space.low, env.action_space.high  # type: ignore[attr-defined]
    observations = env.reset()
    returns, running = np.zeros(env.num_envs), np.ones(env.num_envs, dtype=bool)
    squashed = []  # the actions of the envs still in their first episode, in [-1, 1]
    while running.any():
        actions, _ = model.predict(observations, deterministic=True)  # type: ignore[arg-type]
        unit = np.clip(gain * (2.0 * (actions - low) / (high - low) - 1.0), -1.0, 1.0)
        squashed.append(unit[running])
        observations, rewards, dones, _ = env.step(np.clip(low + (unit + 1.0) * 0.5 * (high - low), low, high))
        returns += rewards * running
        running &= ~dones
    return returns, np.concatenate(squashed)


if __name__ == "__main__":
    main()
