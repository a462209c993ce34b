"""
End-to-end env steps per second of ``learn()`` on a GPU, with eager updates and with CUDA graphs
(``cuda_graphs=True``), the two models taking turns in one process so that both see the same machine.

    python benchmarks/cuda_e2e.py                       # Pendulum-v1, the paper's schedule at 64 and 512 envs
    python benchmarks/cuda_e2e.py --n-envs 64 --seconds 20

The envs are Pendulum-v1 in a DummyVecEnv (stepping them is CPU work in Python): the ratio shows how much of
``learn()`` the updates take on a GPU, not a simulator's speed. Timings are printed, never asserted.
"""

import argparse
import functools

import torch as th
from timing import machine, rate, take_turns  # benchmarks/timing.py

import sb3_cgac  # noqa: F401  (before torch: it sets torch's OpenMP spinning)
from sb3_cgac import CGAC
from sb3_cgac.vec_env import make_vec_env


def learn(model: CGAC, steps: int) -> int:
    """Train ``model`` for ``steps`` more env steps; returns how many it took (whole iterations)."""
    before = model.num_timesteps
    model.learn(steps, reset_num_timesteps=False)
    return model.num_timesteps - before


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-envs", type=int, nargs="+", default=[64, 512])
    parser.add_argument("--seconds", type=float, default=8.0, help="timed seconds per candidate and env count")
    parser.add_argument("--device", default="cuda")
    args = parser.parse_args()
    print(f"Machine: {machine(th.get_num_threads(), args.device)}\n")
    print("| envs | candidate | steps/s | speed / eager |\n| --- | --- | --- | --- |")
    for n_envs in args.n_envs:
        models = {
            name: CGAC(
                "MlpPolicy",
                make_vec_env("Pendulum-v1", n_envs=n_envs, seed=0),
                critic_updates_per_step=2,  # the paper's schedule, as measured in docs/performance.md
                device=args.device,
                seed=0,
                cuda_graphs=graphs,
            )
            for name, graphs in (("eager", False), ("cuda_graphs", True))
        }
        for model in models.values():  # fill the window and capture the graphs before timing
            model.learn((model.buffer_window + 10) * n_envs)
        # A chunk is ten iterations (one step of every env each)
        work = {name: functools.partial(learn, model, 10 * n_envs) for name, model in models.items()}
        turns = take_turns(work, chunk=1.0, seconds=args.seconds)
        rates = {name: rate(turn) for name, turn in turns.items()}
        for name, steps_per_second in rates.items():
            print(f"| {n_envs} | {name} | {steps_per_second:,.0f} | {steps_per_second / rates['eager']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
