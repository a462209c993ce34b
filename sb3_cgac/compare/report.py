"""A comparison's outputs from its pairs' evaluations: evaluations.csv, the return plots and summary.md."""

import json
from pathlib import Path
from typing import Any

import numpy as np

from sb3_cgac.compare.files import COLUMNS, finished_pairs, run_paths, train_stats_path


def load_results(out: Path, runs: list[str], seeds: int) -> tuple[Any, dict[tuple[str, int], dict[str, float]]]:
    import pandas as pd

    frames, completed = [], {}
    for run in runs:
        for seed in range(seeds):
            csv_path, done_path, _ = run_paths(out, run, seed)
            if done_path.exists():
                frames.append(pd.read_csv(csv_path))
                completed[(run, seed)] = json.loads(done_path.read_text())
    if not frames:
        raise RuntimeError(f"No finished run in {out}/runs.")
    return pd.concat(frames, ignore_index=True), completed


def aggregate_curves(curves: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray | None, str]:
    """Point estimate and 95% band over seeds: IQM with rliable from 3 seeds, else the mean with a bootstrap band."""
    scores = np.stack(curves)  # seeds x points
    if len(curves) == 1:
        return scores[0], None, "mean"
    if len(curves) >= 3:
        try:
            from rliable import library as rly
            from rliable import metrics
        except Exception:  # not installed, or its dependency arch broken (pandas 3): fall back to the mean
            rly = None
        if rly is not None:

            def iqm(values: np.ndarray) -> np.ndarray:
                return np.array([metrics.aggregate_iqm(values[..., point]) for point in range(values.shape[-1])])

            point, band = rly.get_interval_estimates({"run": scores[:, None, :]}, iqm, reps=500)
            return point["run"], band["run"], "IQM"
    rng = np.random.default_rng(0)
    resampled = scores[rng.integers(0, len(curves), (1000, len(curves)))].mean(axis=1)
    return scores.mean(axis=0), np.percentile(resampled, [2.5, 97.5], axis=0), "mean"


def new_axis() -> tuple[Any, Any]:
    """A figure and its axis, drawn without a display (matplotlib's Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(figsize=(7, 4.5))


def save_figure(figure: Any, axis: Any, x_label: str, y_label: str, path: Path) -> None:
    """Label the axis, add a grid and the legend, write the figure to ``path`` and close it."""
    import matplotlib.pyplot as plt

    axis.set_xlabel(x_label)
    axis.set_ylabel(y_label)
    axis.grid(alpha=0.3)
    axis.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def plot(results: Any, runs: list[str], x_column: str, x_label: str, x_scale: float, path: Path) -> None:
    figure, axis = new_axis()
    estimator = "mean"
    for run in runs:
        per_seed = [frame.sort_values(x_column) for _, frame in results[results["run"] == run].groupby("seed")]
        if not per_seed:
            continue
        end = min(frame[x_column].max() for frame in per_seed)
        grid = np.linspace(0, end, 60)
        curves = [np.interp(grid, frame[x_column], frame["mean_return"]) for frame in per_seed]
        point, band, estimator = aggregate_curves(curves)
        axis.plot(grid * x_scale, point, label=f"{run} ({len(per_seed)} seeds)")
        if band is not None:
            axis.fill_between(grid * x_scale, band[0], band[1], alpha=0.2)
    save_figure(figure, axis, x_label, f"evaluation return ({estimator}, 95% band)", path)


def final_training_return(out: Path, run: str, seed: int) -> float:
    """The mean return of a pair's latest training episodes at its last evaluation (nan where not recorded)."""
    import pandas as pd

    path = train_stats_path(out, run, seed)
    if not path.exists():
        return float("nan")
    stats = pd.read_csv(path)
    if "rollout_return" not in stats:
        return float("nan")
    returns = stats["rollout_return"].dropna()
    return float(returns.iloc[-1]) if len(returns) else float("nan")


def first_reach(frame: Any, threshold: float, column: str) -> float:
    reached = frame[frame["mean_return"] >= threshold]
    return float(reached[column].min()) if len(reached) else float("inf")


def choose_threshold(finals: dict[str, Any], threshold: float | None, references: tuple[str, ...]) -> tuple[float, str]:
    """
    :param finals: Each run's final returns by seed
    :return: The threshold (given, else the best final return of the first reference run, else of any run) and what
        it was taken from
    """
    if threshold is not None:
        return threshold, "given"
    # A partial comparison (e.g. `--runs cgac` first) has no reference run yet: take the best final of all runs
    with_results = [run for run, values in finals.items() if len(values) > 0]  # load_results found at least one
    if references[0] in with_results:
        source, sources = f"best of {references[0]}'s final returns", [references[0]]
    else:
        source, sources = f"best final return of any run; no {references[0]} run yet", with_results
    return float(max(finals[run].max() for run in sources)), source


def run_statistics(
    out: Path, results: Any, run: str, done: list[dict[str, float]], threshold: float, metric_columns: list[str]
) -> dict[str, float]:
    """
    The summary's numbers for one run: finals, bests, steps/s, time and steps to the threshold, the last success rate
    and ``--metrics`` values, and the final training return (means over seeds where not said otherwise).

    :param results: Every pair's evaluations (``evaluations.csv``)
    :param done: The completion records of the run's finished seeds
    """
    mine = results[results["run"] == run]
    last = mine.sort_values("steps").groupby("seed")
    finals = last["mean_return"].last()
    # The evaluation before training is left out: an untrained policy can score well (a motionless Ant
    # collects its healthy reward for 1000 steps) and would count as reaching the threshold at 0 s
    frames = [frame[frame["steps"] > 0] for _, frame in mine.groupby("seed")]
    times = [first_reach(frame, threshold, "seconds") for frame in frames]
    steps = [first_reach(frame, threshold, "steps") for frame in frames]
    stats = {
        "seeds": len(frames),
        "final": float(finals.mean()),
        "final_std": float(finals.std(ddof=0)),
        "worst": float(finals.min()),
        "best": float(np.mean([frame["mean_return"].max() for frame in frames])),
        "sps": float(np.mean([d["steps"] / d["seconds"] for d in done])),
        "reached": int(np.isfinite(times).sum()),
        # Median over seeds, a seed that never reaches the threshold counting as infinitely slow
        "time": float(np.median(times)),
        "steps": float(np.median(steps)),
    }
    if "success_rate" in results:  # runs evaluated without --success-key have no rate
        stats["success"] = float(last["success_rate"].last().mean())
    for key in metric_columns:
        stats[f"metric {key}"] = float(last[key].last().mean())
    # A few deterministic episodes make a noisy final evaluation; the training envs' latest 100 episodes (the
    # stochastic policy) tell where each seed ended more steadily
    training = [final_training_return(out, run, int(seed)) for seed in finals.index]
    stats["training"] = float(np.nanmean(training)) if np.isfinite(training).any() else float("nan")
    return stats


def time_ratio(stats: dict[str, dict[str, float]], run: str, reference: str) -> str:
    """The run's time to the threshold over the reference's, as the table shows it."""
    if reference not in stats or run == reference:
        return "-"
    mine, theirs = stats[run]["time"], stats[reference]["time"]
    if not np.isfinite(mine):
        return "never"
    if not np.isfinite(theirs):
        return "< 1 (ref. never)"
    return f"{mine / theirs:.2f}x" if theirs > 0 else "-"


def summary_table(
    stats: dict[str, dict[str, float]],
    threshold: float,
    threshold_source: str,
    references: tuple[str, ...],
    with_success: bool,
    metric_columns: list[str],
) -> str:
    """summary.md: the note on how the columns are computed, and one row per run."""
    shown = [reference for reference in references if reference in stats]
    with_training = any(np.isfinite(s["training"]) for s in stats.values())
    training_note = " Final training return: mean over seeds of the training envs' latest episodes at the last evaluation."
    lines = [
        f"Threshold: {threshold:.1f} ({threshold_source}). "
        "Time and steps to threshold are medians over seeds of the training wall-clock and env steps at the first "
        "evaluation at or above it (so they are only as fine as the evaluation interval); final and best return: "
        "mean over seeds of the last and best evaluation (+/- std over seeds); worst final: the lowest last evaluation "
        "of any seed." + (training_note if with_training else "") + " The evaluation before training counts "
        "in neither the best return nor the threshold. Ratios below 1 mean faster than the reference.",
        "",
        "| run | seeds | final return | worst final | best return | steps/s | time to threshold | steps to threshold |"
        + "".join(f" time vs {reference} |" for reference in shown)
        + (" final success rate |" if with_success else "")
        + "".join(f" final {key} |" for key in metric_columns)
        + (" final training return |" if with_training else ""),
        "| --- | --- | --- | --- | --- | --- | --- | --- |"
        + " --- |" * (len(shown) + with_success + len(metric_columns) + with_training),
    ]
    for run, s in stats.items():
        time_text = (
            "not reached"
            if not np.isfinite(s["time"])
            else (f"{s['time']:.0f} s" if s["time"] < 120 else f"{s['time'] / 60:.1f} min")
        )
        steps_text = f"{s['steps']:,.0f}" if np.isfinite(s["steps"]) else "-"
        lines.append(
            f"| {run} | {s['seeds']} | {s['final']:.0f} +/- {s['final_std']:.0f} | {s['worst']:.0f} | {s['best']:.0f} "
            f"| {s['sps']:,.0f} "
            f"| {time_text} ({s['reached']}/{s['seeds']} seeds) | {steps_text} |"
            + "".join(f" {time_ratio(stats, run, reference)} |" for reference in shown)
            + (f" {s['success']:.2f} |" if with_success else "")
            + "".join(f" {s[f'metric {key}']:.4g} |" for key in metric_columns)
            + ((f" {s['training']:.0f} |" if np.isfinite(s["training"]) else " - |") if with_training else "")
        )
    return "\n".join(lines)


def summarise(
    out: Path, runs: list[str], seeds: int, threshold: float | None, references: tuple[str, ...] = ("ppo", "sac")
) -> str:
    """
    Write evaluations.csv, the two plots and summary.md; return the markdown table. They cover ``runs`` (seeds
    ``0 .. seeds - 1``) and every other finished pair in ``out/runs``: a comparison that adds a run or a seed to a
    folder never drops the folder's earlier runs from its outputs.

    :param references: Runs whose time to threshold the others are compared with; the threshold defaults to the
        best final return of the first of them
    """
    found = finished_pairs(out)
    runs = [*runs, *sorted({run for run, _ in found} - set(runs))]
    seeds = max([seeds, *(seed + 1 for _, seed in found)])
    results, completed = load_results(out, runs, seeds)
    results.sort_values(["run", "seed", "steps"]).to_csv(out / "evaluations.csv", index=False)
    plot(results, runs, "steps", "env steps", 1.0, out / "return_vs_steps.png")
    plot(results, runs, "seconds", "training wall-clock (minutes)", 1 / 60, out / "return_vs_time.png")

    finals = {run: results[results["run"] == run].sort_values("steps").groupby("seed")["mean_return"].last() for run in runs}
    threshold, threshold_source = choose_threshold(finals, threshold, references)
    # The --metrics columns: every column after the fixed ones
    metric_columns = [column for column in results.columns if column not in (*COLUMNS, "success_rate")]
    stats = {}
    for run in runs:
        done = [completed[(run, seed)] for seed in range(seeds) if (run, seed) in completed]
        stats[run] = run_statistics(out, results, run, done, threshold, metric_columns)
    table = summary_table(stats, threshold, threshold_source, references, "success_rate" in results, metric_columns)
    (out / "summary.md").write_text(table + "\n")
    print(table)
    return table
