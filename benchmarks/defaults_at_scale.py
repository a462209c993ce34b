"""
Learning curves of the bare defaults, ``CGAC("MlpPolicy", make_vec_env(env_id, n_envs))``, or of variants of them,
at large env counts and several seeds at once: for a machine with many cores (and a GPU), where the 2-core VMs of
this project cannot give 1024 or 4096 envs the millions of steps they need. It needs no rl_zoo3::

    python benchmarks/defaults_at_scale.py --n-envs 1024 4096 --seeds 4 --minutes 6 --device cuda --cuda-graphs \\
        --out results

Every (env count, seed) pair trains in its own process with one torch thread, all at once (``--jobs`` caps them).
Evaluations are deterministic, ``--eval-episodes`` episodes on separate envs, every ``--eval-every`` env steps and
at the end; the budget is training wall-clock (evaluations not counted) or env steps, whichever ends first.
Each env count gets a folder ``<out>/<env>-defaults-<n>-envs-<device>[-<name>]`` in the layout of ``sb3_cgac.compare``
(``runs/cgac_seed<k>.csv``, ``.json``, ``_train.csv``, ``.log``), so that its summary, plots and table come from::

    python -m sb3_cgac.compare --env Pendulum-v1 --runs cgac --seeds 4 --threshold -200 --summary-only --out FOLDER

``--cuda-graphs`` replays each update as a CUDA graph: the same arithmetic as eager updates (tests/test_cuda_graphs.py),
so the curves are the defaults'. Nothing is timed against anything: steps/s depend on how many runs share the machine.
"""

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from sb3_cgac.compare import COLUMNS, record_train_stats, run_paths, train_stats_path, write_csv_atomically

# The options a worker gets from the command line of the parent
FORWARDED = ("env", "minutes", "steps", "eval_every", "eval_episodes", "eval_envs", "device", "out", "overrides", "name")


def folder(args: argparse.Namespace, n_envs: int) -> Path:
    suffix = f"-{args.name}" if args.name else ""
    return Path(args.out) / f"{args.env}-defaults-{n_envs}-envs-{args.device}{suffix}"


def train_one(args: argparse.Namespace) -> None:
    """One (env count, seed) pair: train the bare defaults under the budget, writing evaluations as it goes."""
    import torch as th
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.evaluation import evaluate_policy

    from sb3_cgac import CGAC  # sb3_cgac, imported above, set torch's OpenMP spinning before torch loaded
    from sb3_cgac.vec_env import make_vec_env

    th.set_num_threads(1)
    out = folder(args, args.n_envs[0])
    csv_path, done_path, _ = run_paths(out, "cgac", args.seed)
    env = make_vec_env(args.env, n_envs=args.n_envs[0], seed=args.seed)
    eval_env = make_vec_env(args.env, n_envs=args.eval_envs, seed=args.seed + 10_000, random_first_episode=False)
    kwargs = json.loads(args.overrides)
    model = CGAC("MlpPolicy", env, seed=args.seed, device=args.device, cuda_graphs=args.cuda_graphs, **kwargs)
    rows: list[str] = [",".join(COLUMNS)]
    train_rows: list[dict[str, str]] = []

    class Evaluate(BaseCallback):
        def _on_training_start(self) -> None:
            self.seconds, self.resumed, self.next_evaluation = 0.0, time.perf_counter(), 0
            self.evaluate()

        def clock(self) -> float:
            return self.seconds + time.perf_counter() - self.resumed

        def evaluate(self) -> None:
            self.seconds = self.clock()
            self.next_evaluation = self.num_timesteps + args.eval_every
            returns, lengths = evaluate_policy(
                self.model, eval_env, n_eval_episodes=args.eval_episodes, deterministic=True, return_episode_rewards=True
            )
            mean_return = float(np.mean(returns))
            rows.append(f"cgac,{args.seed},{self.num_timesteps},{self.seconds:.2f},{mean_return:.3f},{np.mean(lengths):.1f}")
            write_csv_atomically(csv_path, "\n".join(rows) + "\n")
            stats_path = train_stats_path(out, "cgac", args.seed)
            logged, episodes = self.model.logger.name_to_value, self.model.ep_info_buffer or ()
            record_train_stats(stats_path, train_rows, logged, self.num_timesteps, self.seconds, episodes)
            print(
                f"{args.n_envs[0]} envs seed {args.seed}: {self.num_timesteps} steps, {self.seconds:.0f} s, "
                f"return {mean_return:.1f}",
                flush=True,
            )
            self.resumed = time.perf_counter()

        def _on_step(self) -> bool:
            if self.clock() >= args.minutes * 60 or self.num_timesteps >= args.steps:
                return False
            if self.num_timesteps >= self.next_evaluation:
                self.evaluate()
            return True

        def _on_training_end(self) -> None:
            self.evaluate()

    evaluator = Evaluate()
    model.learn(args.steps, callback=evaluator)
    done_path.write_text(json.dumps({"steps": model.num_timesteps, "seconds": evaluator.seconds}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Pendulum-v1")
    parser.add_argument("--n-envs", type=int, nargs="+", default=[1024, 4096])
    parser.add_argument("--seeds", type=int, default=3, help="how many seeds of each env count")
    parser.add_argument("--first-seed", type=int, default=0, help="seeds first-seed .. first-seed + seeds - 1")
    parser.add_argument("--minutes", type=float, default=6.0, help="training wall-clock per run (evaluations not counted)")
    parser.add_argument("--steps", type=int, default=10**12, help="env steps per run (the other budget)")
    parser.add_argument("--eval-every", type=int, default=163_840, help="env steps between evaluations")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--eval-envs", type=int, default=10)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--cuda-graphs", action="store_true", help="replay the updates as CUDA graphs (same arithmetic)")
    parser.add_argument("--overrides", default="{}", help="CGAC arguments over the defaults, as JSON: '{\"tau\": 0.02}'")
    parser.add_argument("--name", default="", help="suffix of the output folders (a variant's name, e.g. tau-0.02)")
    parser.add_argument("--jobs", type=int, default=None, help="runs at once (default: all)")
    parser.add_argument("--out", default="results")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--seed", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        train_one(args)
        return
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    pairs = [(n_envs, seed) for n_envs in args.n_envs for seed in seeds]
    running: dict[tuple[int, int], subprocess.Popen] = {}
    failed = []
    while pairs or running:
        while pairs and len(running) < (args.jobs or len(pairs) + len(running)):
            n_envs, seed = pairs.pop(0)
            log_path = run_paths(folder(args, n_envs), "cgac", seed)[2]
            log_path.parent.mkdir(parents=True, exist_ok=True)
            command = [sys.executable, __file__, "--worker", "--n-envs", str(n_envs), "--seed", str(seed)]
            command += [f"--{option.replace('_', '-')}={getattr(args, option)}" for option in FORWARDED]
            command += ["--cuda-graphs"] if args.cuda_graphs else []
            with log_path.open("w") as log:  # the worker keeps its own copy of the handle
                running[(n_envs, seed)] = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
        time.sleep(2)
        for pair, process in list(running.items()):
            if process.poll() is not None:
                del running[pair]
                print(f"{pair[0]} envs seed {pair[1]}: exit code {process.returncode}", flush=True)
                if process.returncode != 0:
                    failed.append(pair)
                    print(run_paths(folder(args, pair[0]), "cgac", pair[1])[2].read_text()[-3000:], flush=True)
    if failed:
        raise SystemExit(f"Failed: {failed}")


if __name__ == "__main__":
    main()
