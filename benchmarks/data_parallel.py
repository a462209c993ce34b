"""
Data-parallel CGAC on one machine: N ranks of one thread each (``torchrun``, ``sb3_cgac.common.distributed``) against one
process with N threads, on the same zoo entry and wall-clock budget, measured side by side in one run.

    python benchmarks/data_parallel.py --seeds 3 --minutes 10 --out docs/results/data-parallel-HalfCheetah-v5

Both set-ups use every core of the machine, so they run one at a time, taking turns seed by seed (A0, B0, A1, B1...)
so that the machine's drift hits both alike. Each set-up is one ``python -m sb3_cgac.compare`` folder (finished seeds
are skipped when the command runs again). The env count and the batch of the entry are per rank: the ranks step
N times as many envs as the single process. The table gives env steps/s (all ranks), the final evaluation return at
the budget, and the return per env step: each run's evaluation return interpolated at the env steps that both runs of
the seed reached (the fewer of their final counts), seed by seed.
"""

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from timing import machine  # benchmarks/timing.py


def compare_command(args: argparse.Namespace, out: Path, seed: int, nproc: int, threads: int) -> list[str]:
    command = [sys.executable, "-m", "sb3_cgac.compare", "--env", args.env, "--runs", args.run]
    command += ["--seeds", "1", "--first-seed", str(seed), "--minutes", str(args.minutes)]
    command += ["--eval-every", str(args.eval_every), "--backend", args.backend, "--jobs", "1"]
    command += ["--threads", str(threads), "--nproc-per-run", str(nproc), "--out", str(out)]
    return command


def final_rows(folder: Path, run: str) -> pd.DataFrame:
    frame = pd.read_csv(folder / "evaluations.csv")
    return frame[frame["run"] == run].sort_values("steps")


def table(args: argparse.Namespace, parallel: Path, single: Path) -> str:
    par, one = final_rows(parallel, args.run), final_rows(single, args.run)
    lines = [
        f"Machine: {machine(threads=1)}; {args.env}, entry `{args.run}`, backend {args.backend}, {args.minutes} min per run",
        "",
        "| seed | set-up | env steps | steps/s | final return | return at the env steps both reached |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    ratios, at_equal_steps = [], []
    for seed in sorted(set(one["seed"]) & set(par["seed"])):
        runs = {
            f"{args.nproc} ranks x 1 thread": par[par["seed"] == seed],
            f"1 process x {args.nproc} threads": one[one["seed"] == seed],
        }
        common = min(frame["steps"].iloc[-1] for frame in runs.values())
        found = []
        for name, frame in runs.items():
            rate = frame["steps"].iloc[-1] / frame["seconds"].iloc[-1]
            at_common = float(np.interp(common, frame["steps"], frame["mean_return"]))
            found.append((rate, at_common))
            steps, final = frame["steps"].iloc[-1], frame["mean_return"].iloc[-1]
            lines.append(f"| {seed} | {name} | {steps:,} | {rate:,.0f} | {final:,.0f} | {at_common:,.0f} ({common:,}) |")
        ratios.append(found[0][0] / found[1][0])
        at_equal_steps.append((found[0][1], found[1][1]))
    if ratios:
        p_mean, o_mean = np.mean([a for a, _ in at_equal_steps]), np.mean([b for _, b in at_equal_steps])
        lines += [
            "",
            f"steps/s ratio (ranks / one process), per seed: {', '.join(f'{r:.2f}' for r in ratios)}; "
            f"mean {np.mean(ratios):.2f}",
            f"return at the env steps both reached (ranks / one process), mean over seeds: {p_mean:,.0f} / {o_mean:,.0f}",
        ]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="HalfCheetah-v5")
    parser.add_argument("--run", default="cgac", help="hyperparameter file (entry) of both set-ups")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--eval-every", type=float, default=1.0, help="minutes")
    parser.add_argument("--backend", default="envpool")
    parser.add_argument("--nproc", type=int, default=2, help="ranks of one thread, against one process of that many threads")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--table-only", action="store_true")
    args = parser.parse_args()

    parallel = args.out / f"{args.nproc}-ranks-1-thread"
    single = args.out / f"1-process-{args.nproc}-threads"
    if not args.table_only:
        for seed in range(args.seeds):
            for folder, nproc, threads in ((parallel, args.nproc, 1), (single, 1, args.nproc)):
                subprocess.run(compare_command(args, folder, seed, nproc, threads), check=True)
    text = table(args, parallel, single)
    (args.out / "summary.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
