"""
Draw compare's return-against-time (or -steps) plot from the evaluations of one or more result folders, e.g. the
README's figure::

    python experiments/figure.py docs/results/Humanoid-v5-ant-recipe docs/results/Humanoid-v5-ppo-sac-same-vm \\
        --runs cgac=cgac_antrecipe_floor4e4_predict ppo sac --seeds cgac=6,7,8,9 --out docs/figures/Humanoid-v5.png

``--runs name=run`` renames a run (the entry's folder name) for the legend; ``--seeds name=a,b`` keeps those seeds of it.
A run is drawn from the first folder (in the order given) that holds it.
"""

import argparse
from pathlib import Path

import pandas as pd

from sb3_cgac.compare import plot


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("::")[0].strip())
    parser.add_argument("folders", nargs="+", help="result folders with an evaluations.csv")
    parser.add_argument("--runs", nargs="+", required=True, help="runs to draw, in order; name=run renames one")
    parser.add_argument("--seeds", nargs="*", default=[], help="name=a,b,...: the seeds of a run to draw (default: all)")
    parser.add_argument("--x", choices=["seconds", "steps"], default="seconds")
    parser.add_argument("--out", required=True, help="the PNG to write")
    args = parser.parse_args()
    renames = dict(item.split("=", 1) if "=" in item else (item, item) for item in args.runs)
    frames, taken = [], set[str]()
    for folder in args.folders:
        frame = pd.read_csv(Path(folder) / "evaluations.csv")
        wanted = set(renames.values()) - taken
        frames.append(frame[frame["run"].isin(wanted)])
        taken |= wanted & set(frame["run"])
    results = pd.concat(frames, ignore_index=True)
    results["run"] = results["run"].map({run: name for name, run in renames.items()})
    for item in args.seeds:
        name, seeds = item.split("=", 1)
        keep = results["seed"].isin([int(seed) for seed in seeds.split(",")])
        results = results[(results["run"] != name) | keep]
    label, scale = ("training wall-clock (minutes)", 1 / 60) if args.x == "seconds" else ("env steps", 1.0)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    plot(results, list(renames), args.x, label, scale, Path(args.out))


if __name__ == "__main__":
    main()
