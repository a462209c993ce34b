"""
Time to a fixed fraction of the best return against the number of action dimensions, across comparisons made by
``sb3_cgac.compare`` (the paper's claim: CGAC's lead grows with the action space)::

    python experiments/scaling.py docs/results/Pendulum-v1 docs/results/Hopper-v5 docs/results/myoLegWalk-v0:80 \\
        --out docs/results/scaling

Each argument is a comparison folder named after its env id (``Ant-v5``, or ``Ant-v5-<anything>`` for a variant),
with ``:<n>`` for the number of action dimensions when the env is not installed here (MyoSuite has its own
environment). Folders of one env joined by ``+`` (``docs/results/Ant-v5-no-policy-averaging+docs/results/Ant-v5``)
take each run from the first folder that has it: a new CGAC entry beside the PPO runs of an older comparison.

A run of ``--runs`` may be a series drawn from differently named runs: ``cgac=cgac_gamma0995,cgac`` plots, for each
folder, the first of ``cgac_gamma0995`` and ``cgac`` that it has, as ``cgac`` (entries tuned in variant folders under
their own run names beside the older entries' ``cgac``); the table names the run taken where it is not the series.

For each run (``--runs``) and seed, the time to a fraction ``f`` of the seed's own best is the training wall-clock
of its first evaluation at or above ``first + f * (best - first)``, ``first`` being the evaluation before training
(so negative returns work); the median over seeds is plotted against the action dimensions, and tabulated. A seed
that never improves counts as not reaching it.
"""

import argparse
import re
from pathlib import Path
from typing import Any

import numpy as np

from sb3_cgac.compare import new_axis, save_figure


def action_dims(env_id: str) -> int:
    """Number of action dimensions of an installed env (gymnasium-robotics and MyoSuite registered if present)."""
    import gymnasium as gym

    from sb3_cgac.vec_env import register_optional_envs

    register_optional_envs()
    if env_id not in gym.registry:
        raise ValueError(f"{env_id} is not installed here: pass its action dimensions as <folder>:<n>.")
    env = gym.make(env_id)
    shape = env.action_space.shape
    env.close()
    if not shape:
        raise ValueError(f"{env_id} has no Box action space.")
    return int(np.prod(shape))


def time_to_fraction(frame: Any, fraction: float) -> float:
    """Seconds to the first evaluation at ``fraction`` of this seed's improvement over its first evaluation."""
    frame = frame.sort_values("steps")
    first, best = float(frame["mean_return"].iloc[0]), float(frame["mean_return"].max())
    if best <= first:
        return float("inf")
    reached = frame[(frame["steps"] > 0) & (frame["mean_return"] >= first + fraction * (best - first))]
    return float(reached["seconds"].min()) if len(reached) else float("inf")


def env_id_of(folder: str) -> str:
    """The env id a comparison folder is named after: its name up to the version suffix (``Ant-v5-no-x`` -> ``Ant-v5``)."""
    match = re.match(r"(.+?-v\d+)(-|$)", Path(folder).name)
    if match is None:
        raise ValueError(f"{folder} is not named after an env id (such as Ant-v5 or Ant-v5-<variant>): rename it.")
    return match.group(1)


def read_evaluations(argument: str) -> tuple[str, Any]:
    """Env id and evaluations of ``<folder>[+<folder>...]``: each run from the first folder that has it."""
    import pandas as pd

    folders = argument.split("+")
    env_ids = {env_id_of(folder) for folder in folders}
    if len(env_ids) != 1:
        raise ValueError(f"{argument} joins folders of different envs ({', '.join(sorted(env_ids))}): join one env's only.")
    frames: list[Any] = []
    runs_seen: set[str] = set()
    for folder in folders:
        results = pd.read_csv(Path(folder) / "evaluations.csv")
        frames.append(results[~results["run"].isin(runs_seen)])
        runs_seen |= set(results["run"])
    return env_ids.pop(), pd.concat(frames, ignore_index=True)


def parse_series(runs: list[str]) -> dict[str, list[str]]:
    """``name`` or ``name=run[,run...]`` of ``--runs``: each series and the run names it may take, in order."""
    series: dict[str, list[str]] = {}
    for argument in runs:
        name, equals, sources = argument.partition("=")
        names = [source for source in sources.split(",") if source] if equals else [name]
        if not name or not names:
            raise ValueError(f"--runs {argument!r}: write a run name, or <series>=<run>[,<run>...].")
        if name in series:
            raise ValueError(f"--runs names the series {name!r} twice: give it once, with all its run names.")
        series[name] = names
    return series


def scaling_table(folders: list[str], series: dict[str, list[str]], fraction: float) -> list[dict[str, Any]]:
    """One row per (env, series): env id, action dimensions, run taken, seeds, median seconds to the fraction."""
    rows = []
    for argument in folders:
        joined, _, dims_text = argument.partition(":")
        env_id, results = read_evaluations(joined)
        dims = int(dims_text) if dims_text else action_dims(env_id)
        available = set(results["run"])
        for name, sources in series.items():
            run = next((source for source in sources if source in available), None)
            if run is None:
                continue
            seeds = [frame for _, frame in results[results["run"] == run].groupby("seed")]
            times = [time_to_fraction(frame, fraction) for frame in seeds]
            rows.append(dict(env=env_id, dims=dims, run=name, source=run, seeds=len(seeds), seconds=float(np.median(times))))
    return sorted(rows, key=lambda row: (row["dims"], row["env"], row["run"]))


def plot_scaling(rows: list[dict[str, Any]], runs: list[str], fraction: float, path: Path) -> None:
    figure, axis = new_axis()
    for run in runs:
        points = [(row["dims"], row["seconds"] / 60) for row in rows if row["run"] == run and np.isfinite(row["seconds"])]
        if points:
            dims, minutes = zip(*points, strict=True)
            axis.plot(dims, minutes, "o-", label=run)
    for row in rows:
        axis.annotate(row["env"], (row["dims"], 0), textcoords="offset points", xytext=(0, 4), rotation=90, fontsize=7)
    axis.set_xscale("log")
    y_label = f"minutes to {fraction:.0%} of the best return (median over seeds)"
    save_figure(figure, axis, "action dimensions", y_label, path)


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "folders", nargs="+", help="comparison folders named after their env id: <folder>[+<folder>...][:<dims>]"
    )
    parser.add_argument(
        "--runs", nargs="+", default=["cgac", "ppo"], help="runs to compare: <run>, or <series>=<run>[,<run>...]"
    )
    parser.add_argument("--fraction", type=float, default=0.8, help="fraction of each seed's best improvement")
    parser.add_argument("--out", default="results/scaling", help="output stem: <out>.png and <out>.md")
    args = parser.parse_args(argv)
    if not 0 < args.fraction <= 1:
        raise ValueError(f"--fraction must be in (0, 1], got {args.fraction}.")
    # Parsed before any folder is read, so that a malformed --runs fails first
    series = parse_series(args.runs)
    names = list(series)
    rows = scaling_table(args.folders, series, args.fraction)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    plot_scaling(rows, names, args.fraction, out.with_name(out.name + ".png"))

    def minutes(seconds: float) -> str:
        return f"{seconds / 60:.1f}" if np.isfinite(seconds) else "not reached"

    def cell(row: dict[str, Any]) -> str:
        taken = f", {row['source']}" if row["source"] != row["run"] else ""
        return f"{minutes(row['seconds'])} ({row['seeds']} seed{'s' * (row['seeds'] != 1)}{taken})"

    lines = [
        f"Minutes of training to {args.fraction:.0%} of each seed's best improvement over its first evaluation "
        "(median over seeds).",
        "",
        "| env | action dims | " + " | ".join(names) + " |",
        "| --- | --- | " + " | ".join("---" for _ in names) + " |",
    ]
    for env_id in dict.fromkeys(row["env"] for row in rows):
        of_env = {row["run"]: row for row in rows if row["env"] == env_id}
        cells = [cell(of_env[name]) if name in of_env else "-" for name in names]
        dims = next(iter(of_env.values()))["dims"]
        lines.append(f"| {env_id} | {dims} | " + " | ".join(cells) + " |")
    table = "\n".join(lines)
    out.with_name(out.name + ".md").write_text(table + "\n")
    print(table)
    return table


if __name__ == "__main__":
    main()
