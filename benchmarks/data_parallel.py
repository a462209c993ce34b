"""
Data-parallel CGAC on one machine: N ranks of one thread each (``torchrun``, ``sb3_cgac.distributed``) against one
process with N threads, on the same zoo entry and wall-clock budget, measured side by side in one run.

    python benchmarks/data_parallel.py --seeds 3 --minutes 10 --out docs/results/data-parallel-HalfCheetah-v5

Both set-ups use every core of the machine, so they run one at a time, taking turns seed by seed (A0, B0, A1, B1...)
so that the machine's drift hits both alike. Each set-up is one ``python -m sb3_cgac.compare`` folder (finished seeds
are skipped when the command runs again). The env count and the batch of the entry are per rank: the ranks step
N times as many envs as the single process. The table gives env steps/s (all ranks), the final evaluation return at
the budget, and the return per env step: the data-parallel run's evaluation return interpolated at the env steps
that the single process reached, beside the single process's final return, seed by seed.
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
        "| seed | set-up | env steps | steps/s | final return | return at the single process's final steps |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    ratios, at_equal_steps = [], []
    for seed in sorted(set(one["seed"]) & set(par["seed"])):
        p, o = par[par["seed"] == seed], one[one["seed"] == seed]
        p_rate = p["steps"].iloc[-1] / p["seconds"].iloc[-1]
        o_rate = o["steps"].iloc[-1] / o["seconds"].iloc[-1]
        o_steps = o["steps"].iloc[-1]
        p_at = float(np.interp(o_steps, p["steps"], p["mean_return"]))
        ratios.append(p_rate / o_rate)
        at_equal_steps.append((p_at, o["mean_return"].iloc[-1]))
        p_final, o_final = p["mean_return"].iloc[-1], o["mean_return"].iloc[-1]
        ranks, one_process = f"{args.nproc} ranks x 1 thread", f"1 process x {args.nproc} threads"
        lines.append(f"| {seed} | {ranks} | {p['steps'].iloc[-1]:,} | {p_rate:,.0f} | {p_final:,.0f} | {p_at:,.0f} |")
        lines.append(f"| {seed} | {one_process} | {o_steps:,} | {o_rate:,.0f} | {o_final:,.0f} | - |")
    if ratios:
        p_mean, o_mean = np.mean([a for a, _ in at_equal_steps]), np.mean([b for _, b in at_equal_steps])
        lines += [
            "",
            f"steps/s ratio (ranks / one process), per seed: {', '.join(f'{r:.2f}' for r in ratios)}; "
            f"mean {np.mean(ratios):.2f}",
            f"return at equal env steps (ranks / one process), mean over seeds: {p_mean:,.0f} / {o_mean:,.0f}",
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
