"""
The seconds of a MuJoCo Playground task's first calls through ``PlaygroundVectorEnv``: building it, the first reset,
the first and second steps, a partial reset and the step after it. The first of each compiles; a call that compiles
again shows as seconds where a compiled call takes milliseconds. One process per run: the compilations are cached
per process.

    python benchmarks/playground_compile.py --task CheetahRun --envs 256
"""

import argparse
import time

import torch as th

from sb3_cgac.vec_env.playground_vec_env import PlaygroundVectorEnv


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="CheetahRun")
    parser.add_argument("--envs", type=int, default=256)
    parser.add_argument("--impl", default="jax", help="MuJoCo's JAX implementation: jax (MJX) or warp")
    args = parser.parse_args()
    start = time.perf_counter()
    env = PlaygroundVectorEnv(args.task, args.envs, impl=args.impl)
    actions = th.zeros(args.envs, env.single_action_space.shape[0], device=env.device)  # type: ignore[index]
    mask = th.arange(args.envs, device=env.device) % 2 == 0
    calls = {
        "build": None,
        "reset": lambda: env.reset(seed=0),
        "first step": lambda: env.step(actions),
        "second step": lambda: env.step(actions),
        "partial reset": lambda: env.reset(options={"reset_mask": mask}),
        "step after it": lambda: env.step(actions),
    }
    print(f"{args.task}, {args.envs} envs, impl={args.impl}\n\n| call | seconds |\n| --- | --- |")
    for name, call in calls.items():
        if call is not None:
            start = time.perf_counter()
            obs = call()[0]
            (next(iter(obs.values())) if isinstance(obs, dict) else obs).sum().item()  # waits for the device
        print(f"| {name} | {time.perf_counter() - start:.3f} |", flush=True)


if __name__ == "__main__":
    main()
