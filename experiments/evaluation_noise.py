"""
How far compare's deterministic evaluations stray from the training returns, per seed and over the last evaluations,
e.g. the LeapCube table and figures of docs/results.md ("What 10 evaluation episodes hide on LeapCube")::

    python experiments/evaluation_noise.py docs/results/LeapCubeReorient-v1-{critic-screen-4,critic-screen-5} \
        docs/results/LeapCubeReorient-v1-{critic-screen-6r3,critic-screen-7,critic-screen-7r1,critic-wallclock} \
        docs/results/LeapCubeReorient-v1-{entry,cheap,deviation,predict}-wallclock

A folder's training returns are the ``rollout_return`` column (the mean return of the training envs' latest 100
episodes at each evaluation) of its finished runs' ``runs/<run>_seed<k>_train.csv``, or of its
``training_returns.csv`` where the per-run files are not kept; ``--write`` collects the former into the latter. For
every (run, seed) it prints the last evaluation and the last training return, each with its ratio to its own best of
the last ``--last`` evaluations, then the mean and std of (evaluation - training return) over those evaluations:
CGAC's runs together, the others per run.
"""

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from sb3_cgac.compare.files import finished_pairs, train_stats_path

TRAINING_COLUMNS = ["run", "seed", "steps", "seconds", "rollout_return", "rollout_length"]


def training_returns(folder: Path) -> pd.DataFrame:
    """
    The training returns of every finished (run, seed) of a compare folder, from its per-run files or its collected
    CSV. A run still training (no completion record) is left out, as compare leaves it out of ``evaluations.csv``.
    """
    paths = {(run, seed): train_stats_path(folder, run, seed) for run, seed in finished_pairs(folder)}
    paths = {pair: path for pair, path in paths.items() if path.exists()}
    if not paths:
        return pd.read_csv(folder / "training_returns.csv")
    frames = [
        pd.read_csv(path).assign(run=run, seed=seed).reindex(columns=TRAINING_COLUMNS) for (run, seed), path in paths.items()
    ]
    return pd.concat(frames, ignore_index=True)


def per_seed(evaluations: pd.DataFrame, training: pd.DataFrame, last: int) -> pd.DataFrame:
    """One row per (run, seed): final evaluation and training return, their ratios to their late bests, the differences."""
    rows = []
    for (run, seed), evaluated in evaluations.groupby(["run", "seed"]):
        trained = training[(training["run"] == run) & (training["seed"] == seed)].sort_values("steps")
        evaluated = evaluated.sort_values("steps")
        # The pairs share their steps: the training statistics are written at each evaluation
        pairs = evaluated.merge(trained[["steps", "rollout_return"]], on="steps")
        pairs = pairs.dropna(subset=["mean_return", "rollout_return"]).tail(last)
        if pairs.empty:
            continue
        final, trained_final = pairs["mean_return"].iloc[-1], pairs["rollout_return"].iloc[-1]
        rows.append(
            dict(
                run=run,
                seed=seed,
                final=final,
                final_ratio=final / pairs["mean_return"].max(),
                training=trained_final,
                training_ratio=trained_final / pairs["rollout_return"].max(),
                differences=list(pairs["mean_return"] - pairs["rollout_return"]),
            )
        )
    return pd.DataFrame(rows)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("::")[0].strip())
    parser.add_argument("folders", nargs="+", help="compare output folders (evaluations.csv and training returns)")
    parser.add_argument("--last", type=int, default=5, help="evaluations at the end of each seed that count")
    parser.add_argument("--write", action="store_true", help="write each folder's training_returns.csv from runs/")
    args = parser.parse_args(argv)
    if args.last < 1:
        raise ValueError(f"--last must be at least 1, got {args.last}")
    seeds = []
    for name in args.folders:
        folder = Path(name)
        training = training_returns(folder)
        if args.write:
            training.to_csv(folder / "training_returns.csv", index=False)
        table = per_seed(pd.read_csv(folder / "evaluations.csv"), training, args.last)
        seeds.append(table.assign(folder=folder.name))
    results = pd.concat(seeds, ignore_index=True)
    print("| folder | run | seed | final evaluation (x late best) | final training return (x late best) |")
    print("| --- | --- | --- | --- | --- |")
    for row in results.itertuples():
        print(
            f"| {row.folder} | {row.run} | {row.seed} | {row.final:.0f} ({row.final_ratio:.2f}x) "
            f"| {row.training:.0f} ({row.training_ratio:.2f}x) |"
        )
    groups = results["run"].where(~results["run"].str.startswith("cgac"), "cgac (all runs)")
    print()
    for group, frame in results.groupby(groups):
        differences = np.concatenate(frame["differences"].to_numpy())
        print(
            f"{group}: evaluation - training return {differences.mean():+.1f} +/- {differences.std():.1f} "
            f"({len(frame)} seeds, {len(differences)} pairs)"
        )


if __name__ == "__main__":
    main()
