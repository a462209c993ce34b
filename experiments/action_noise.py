"""
How much reward Gaussian exploration noise around the zero action leaves, per noise level: a check of whether an
initial policy standard deviation lets the critics see any reward (Go1's per-step reward is clipped at 0)::

    python experiments/action_noise.py --env Go1JoystickFlatTerrain-v1 --stds 0 0.1 0.2 0.37 0.6 1.0

For each std: actions ``clip(N(0, std), low, high)`` in every env for ``--steps`` steps, then the mean reward per
step, the fraction of steps with a positive reward, and the number and mean length of the episodes that ended.
With ``--episodes N`` it runs until N episodes have ended and gives their mean return (standard error) instead, the
score of a policy that always acts so (std 0: the zero action, a do-nothing policy under delta control)::

    python experiments/action_noise.py --env MuJoCoPlayground/LeapCubeReorient-v1 --stds 0 --episodes 100 --n-envs 50
"""

import argparse
from collections.abc import Iterator
from itertools import islice
from typing import Any

from sb3_cgac.threads import configure_thread_spin

configure_thread_spin()

import numpy as np  # noqa: E402

from sb3_cgac.vec_env import make_vec_env  # noqa: E402


def noisy_steps(env: Any, std: float, seed: int) -> Iterator[tuple[np.ndarray, list[dict]]]:
    """From a reset with ``seed``, step every env with ``clip(N(0, std))`` actions: each step's rewards and ended episodes."""
    low, high = env.action_space.low, env.action_space.high
    env.seed(seed)
    env.reset()
    rng = np.random.default_rng(seed)
    while True:
        actions = np.clip(rng.normal(0.0, std, (env.num_envs, *low.shape)), low, high).astype(np.float32)
        _, reward, dones, infos = env.step(actions)
        yield reward, [infos[i]["episode"] for i in np.flatnonzero(dones) if "episode" in infos[i]]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Go1JoystickFlatTerrain-v1")
    parser.add_argument("--backend", default="envpool")
    parser.add_argument("--n-envs", type=int, default=64)
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--stds", type=float, nargs="+", default=[0.0, 0.1, 0.2, 0.37, 0.6, 1.0])
    parser.add_argument("--episodes", type=int, default=0, help="run until this many episodes ended: their returns")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    env = make_vec_env(args.env, n_envs=args.n_envs, backend=args.backend, seed=args.seed, random_first_episode=False)
    if args.episodes:
        print("| std | episodes | mean return (standard error) | mean length | shortest |")
    else:
        print("| std | reward per step | steps with reward > 0 | episodes ended | their mean length |")
    print("| --- | --- | --- | --- | --- |")
    for std in args.stds:
        steps = noisy_steps(env, std, args.seed)
        if args.episodes:
            ended: list[dict] = []
            while len(ended) < args.episodes:
                ended += next(steps)[1]
            returns, lengths = [e["r"] for e in ended[: args.episodes]], [e["l"] for e in ended[: args.episodes]]
            error = np.std(returns) / np.sqrt(len(returns))
            print(
                f"| {std} | {len(returns)} | {np.mean(returns):.1f} ({error:.1f}) | {np.mean(lengths):.0f} | {min(lengths)} |"
            )
            continue
        rewards, lengths = [], []
        for reward, episodes in islice(steps, args.steps):
            rewards.append(reward)
            lengths += [episode["l"] for episode in episodes]
        rewards_array = np.asarray(rewards)
        mean_length = f"{np.mean(lengths):.1f}" if lengths else "-"
        print(f"| {std} | {rewards_array.mean():.5f} | {(rewards_array > 0).mean():.3f} | {len(lengths)} | {mean_length} |")


if __name__ == "__main__":
    main()
