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

from sb3_cgac.threads import configure_thread_spin

configure_thread_spin()

import numpy as np  # noqa: E402

from sb3_cgac.vec_env import make_vec_env  # noqa: E402


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
    if args.episodes:
        episode_returns(args)
        return

    env = make_vec_env(args.env, n_envs=args.n_envs, backend=args.backend, seed=args.seed, random_first_episode=False)
    low, high = env.action_space.low, env.action_space.high  # type: ignore[attr-defined]
    print("| std | reward per step | steps with reward > 0 | episodes ended | their mean length |")
    print("| --- | --- | --- | --- | --- |")
    for std in args.stds:
        env.seed(args.seed)
        env.reset()
        rng = np.random.default_rng(args.seed)
        rewards, lengths = [], []
        for _ in range(args.steps):
            actions = np.clip(rng.normal(0.0, std, (args.n_envs, *low.shape)), low, high).astype(np.float32)
            _, reward, dones, infos = env.step(actions)
            rewards.append(reward)
            lengths += [infos[i]["episode"]["l"] for i in np.flatnonzero(dones) if "episode" in infos[i]]
        rewards_array = np.asarray(rewards)
        mean_length = f"{np.mean(lengths):.1f}" if lengths else "-"
        print(f"| {std} | {rewards_array.mean():.5f} | {(rewards_array > 0).mean():.3f} | {len(lengths)} | {mean_length} |")


def episode_returns(args: argparse.Namespace) -> None:
    env = make_vec_env(args.env, n_envs=args.n_envs, backend=args.backend, seed=args.seed, random_first_episode=False)
    low, high = env.action_space.low, env.action_space.high  # type: ignore[attr-defined]
    print("| std | episodes | mean return (standard error) | mean length | shortest |")
    print("| --- | --- | --- | --- | --- |")
    for std in args.stds:
        env.seed(args.seed)
        env.reset()
        rng = np.random.default_rng(args.seed)
        returns: list[float] = []
        lengths: list[int] = []
        while len(returns) < args.episodes:
            actions = np.clip(rng.normal(0.0, std, (args.n_envs, *low.shape)), low, high).astype(np.float32)
            _, _, dones, infos = env.step(actions)
            ended = [infos[i]["episode"] for i in np.flatnonzero(dones) if "episode" in infos[i]]
            returns += [episode["r"] for episode in ended]
            lengths += [episode["l"] for episode in ended]
        returns, lengths = returns[: args.episodes], lengths[: args.episodes]
        error, shortest = np.std(returns) / np.sqrt(len(returns)), np.min(lengths)
        print(f"| {std} | {len(returns)} | {np.mean(returns):.1f} ({error:.1f}) | {np.mean(lengths):.0f} | {shortest} |")


if __name__ == "__main__":
    main()
