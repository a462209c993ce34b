"""
The one-setting suite in one command: a named run (and its baselines) on every task of the suite, each task with its
wall-clock budget, env count (its YAML entry's ``n_envs``) and backend, through ``python -m sb3_cgac.compare``
(which resumes finished pairs), then one table and one figure of every task's score normalised to its better
baseline::

    python benchmarks/suite.py --runs defaults=cgac entry=cgac_entry --seeds 3 --conf-dir docs/results/one-setting/conf \\
        --out docs/results/one-setting
    python benchmarks/suite.py --runs defaults=cgac --tasks Pendulum-v1 Hopper-v5 --seeds 2 --no-baselines
    python benchmarks/suite.py --summary-only --out docs/results/one-setting

A run is ``name=file`` (``file``: a YAML file of ``--conf-dir``, default this repository's ``hyperparams/``; the
algorithm is the file name's part before ``_``) or a file name alone. Each task's folder is ``<out>/<task>`` (without
``MuJoCoPlayground/``), with compare's outputs. The suite's outputs, ``<out>/suite.md`` and ``<out>/suite.png``:
per task and run the IQM of the seeds' last evaluations, the same normalised as ``(IQM - untrained) / (best baseline
IQM - untrained)`` (untrained: the mean of every pair's evaluation before training, so that negative returns
normalise too), and the lowest ratio of a seed's last evaluation to its best evaluation of the run's second half
("stays learnt": 1.0 for a seed that ends at its best).
"""

import argparse
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
# The JAX tasks on one core each, as the committed Playground comparisons ran them
JAX_ONE_CORE = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


@dataclass(frozen=True)
class SuiteTask:
    """One task of the suite: its env id, backend, wall-clock budget (minutes) and baselines."""

    env: str
    backend: str
    minutes: float
    baselines: tuple[str, ...]
    extra: tuple[str, ...] = field(default=())

    @property
    def folder(self) -> str:
        return self.env.removeprefix("MuJoCoPlayground/")


MUJOCO_BASELINES = ("ppo", "sac")
SUITE = (
    SuiteTask("Pendulum-v1", "dummy", 4, MUJOCO_BASELINES),
    SuiteTask("HalfCheetah-v5", "envpool", 10, MUJOCO_BASELINES),
    SuiteTask("Hopper-v5", "envpool", 10, MUJOCO_BASELINES),
    SuiteTask("Walker2d-v5", "envpool", 10, MUJOCO_BASELINES),
    SuiteTask("Ant-v5", "envpool", 30, MUJOCO_BASELINES),
    SuiteTask("Humanoid-v5", "envpool", 30, MUJOCO_BASELINES),
    SuiteTask(
        "MuJoCoPlayground/PandaPickCube-v1", "envpool", 20, ("rsl_ppo", "ppo_parallel"), ("--metrics", "reward_box_target")
    ),
    SuiteTask("CheetahRun", "playground", 12, ("rsl_ppo",), ("--eval-envs", "10")),
    # Its episodes score about 0 or 700-900: 50 of them, so that an evaluation's mean does not swing by +-140
    SuiteTask("ReacherHard", "playground", 12, ("rsl_ppo",), ("--eval-episodes", "50", "--eval-envs", "50")),
)
TASKS = {task.env: task for task in SUITE}


def parse_runs(specs: list[str]) -> dict[str, dict[str, Any]]:
    """``["defaults=cgac", "ppo"]`` -> compare's runs: ``{"defaults": {"file": "cgac"}, "ppo": {"file": "ppo"}}``."""
    runs = {}
    for spec in specs:
        name, _, file = spec.partition("=")
        runs[name] = {"file": file or name}
    return runs


def compare_argv(task: SuiteTask, runs: list[str], args: argparse.Namespace) -> list[str]:
    """The arguments of ``python -m sb3_cgac.compare`` for one task of the suite."""
    argv = ["--env", task.env, "--runs", *runs, "--seeds", str(args.seeds), "--first-seed", str(args.first_seed)]
    argv += ["--minutes", str(task.minutes), "--eval-every", str(task.minutes * args.eval_fraction)]
    argv += ["--backend", task.backend, "--jobs", str(args.jobs), "--out", str(Path(args.out) / task.folder), *task.extra]
    return argv + (["--conf-dir", args.conf_dir] if args.conf_dir else [])


def train_task(task: SuiteTask, runs: dict[str, dict[str, Any]], args: argparse.Namespace) -> None:
    """Train (or resume) the named runs and the task's baselines through compare, then write its summary."""
    from sb3_cgac.compare import main as compare_main

    everything = {**runs, **({} if args.no_baselines else {name: {"file": name} for name in task.baselines})}
    if task.backend == "playground":
        os.environ.setdefault("XLA_FLAGS", JAX_ONE_CORE)
    references = task.baselines if not args.no_baselines else (next(iter(runs)),)
    compare_main(runs=everything, argv=compare_argv(task, list(everything), args), references=references)


def late_ratio(returns: np.ndarray, steps: np.ndarray) -> float:
    """A seed's last evaluation over its best of the run's second half (the ratio's inverse for negative returns)."""
    late = returns[steps >= steps.max() / 2]
    best, last = float(late.max()), float(returns[np.argmax(steps)])
    if best <= 0:
        return best / last if last < 0 else 1.0
    return last / best


def iqm(values: np.ndarray) -> float:
    """The mean of the values within their interquartile range (of 3 seeds, the middle one; of 2, their mean)."""
    low, high = np.percentile(values, [25, 75])
    return float(values[(values >= low) & (values <= high)].mean()) if len(values) > 2 else float(np.mean(values))


def task_scores(folder: Path) -> tuple[dict[str, dict[str, float]], float]:
    """
    :return: Per run of a task's folder: seeds, the IQM of the seeds' last evaluations and the lowest late ratio; and
        the mean evaluation before training over every pair (the untrained score)
    """
    import pandas as pd

    results = pd.read_csv(folder / "evaluations.csv")
    untrained = float(results[results["steps"] == 0]["mean_return"].mean())
    scores = {}
    for run, frame in results.groupby("run", sort=False):
        finals, ratios = [], []
        for _, seed_frame in frame.groupby("seed"):
            seed_frame = seed_frame.sort_values("steps")
            finals.append(float(seed_frame["mean_return"].iloc[-1]))
            ratios.append(late_ratio(seed_frame["mean_return"].to_numpy(), seed_frame["steps"].to_numpy()))
        scores[str(run)] = {"seeds": len(finals), "iqm": iqm(np.array(finals)), "late": min(ratios)}
    return scores, untrained


def normalised(score: float, best_baseline: float, untrained: float) -> float:
    span = best_baseline - untrained
    return (score - untrained) / span if span > 0 else float("nan")


def suite_table(out: Path, tasks: list[SuiteTask], runs: list[str]) -> tuple[str, dict[str, dict[str, float]]]:
    """The markdown table of the suite, and each task's normalised score by run."""
    lines = [
        "Per task: IQM of the seeds' last evaluations (seeds), the same normalised to the better baseline "
        "(untrained = 0, better baseline = 1), and the lowest ratio of a seed's last evaluation to its best of the "
        "run's second half.",
        "",
        "| task | baselines | "
        + " | ".join(f"{run}: IQM (seeds) | {run}: normalised | {run}: last / late best" for run in runs)
        + " |",
        "| --- | --- |" + " --- | --- | --- |" * len(runs),
    ]
    normalised_scores: dict[str, dict[str, float]] = {}
    for task in tasks:
        if not (out / task.folder / "evaluations.csv").exists():
            continue
        scores, untrained = task_scores(out / task.folder)
        baselines = [scores[name]["iqm"] for name in task.baselines if name in scores]
        best = max(baselines) if baselines else float("nan")
        row = [task.folder, ", ".join(f"{name} {scores[name]['iqm']:,.0f}" for name in task.baselines if name in scores)]
        normalised_scores[task.folder] = {}
        for run in runs:
            if run not in scores:
                row += ["-", "-", "-"]
                continue
            score = normalised(scores[run]["iqm"], best, untrained)
            normalised_scores[task.folder][run] = score
            row += [f"{scores[run]['iqm']:,.0f} ({scores[run]['seeds']:.0f})", f"{score:.2f}", f"{scores[run]['late']:.2f}"]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines), normalised_scores


def suite_figure(normalised_scores: dict[str, dict[str, float]], runs: list[str], path: Path) -> None:
    """One group of bars per task: each run's score normalised to the better baseline (1, dashed)."""
    from sb3_cgac.compare import new_axis, save_figure

    figure, axis = new_axis()
    tasks = list(normalised_scores)
    width = 0.8 / max(len(runs), 1)
    for index, run in enumerate(runs):
        values = [normalised_scores[task].get(run, np.nan) for task in tasks]
        axis.bar(np.arange(len(tasks)) + index * width, values, width, label=run)
    axis.axhline(1.0, color="black", linestyle="--", linewidth=1)
    axis.set_xticks(np.arange(len(tasks)) + 0.4 - width / 2, tasks, rotation=30, ha="right", fontsize=8)
    save_figure(figure, axis, "task", "IQM normalised to the better baseline", path)


def summarise_suite(out: Path, tasks: list[SuiteTask], runs: list[str]) -> str:
    table, normalised_scores = suite_table(out, tasks, runs)
    (out / "suite.md").write_text(table + "\n")
    if normalised_scores:
        suite_figure(normalised_scores, runs, out / "suite.png")
    print(table)
    return table


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", nargs="+", default=["cgac"], help="runs as name=file (or file), trained on every task")
    parser.add_argument("--tasks", nargs="+", default=[task.env for task in SUITE], choices=list(TASKS))
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--eval-fraction", type=float, default=0.05, help="evaluation interval, a fraction of the budget")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--conf-dir", default=None)
    parser.add_argument("--out", default="results/suite")
    parser.add_argument("--no-baselines", action="store_true", help="train the named runs only")
    parser.add_argument("--summary-only", action="store_true", help="only write the suite's table and figure")
    args = parser.parse_args(argv)
    runs = parse_runs(args.runs)
    tasks = [TASKS[env] for env in args.tasks]
    if not args.summary_only:
        for task in tasks:
            train_task(task, runs, args)
    summarise_suite(Path(args.out), tasks, list(runs))


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    main()
