"""
CGAC vs SB3 PPO vs SB3 SAC on one env, same machine, same budget (needs the ``zoo`` extra, and ``envpool`` for
``--backend envpool``)::

    python -m sb3_cgac.compare --env HalfCheetah-v5 --seeds 3 --minutes 10 --backend envpool --jobs 2 \\
        --out results/HalfCheetah-v5
    python -m sb3_cgac.compare --env Pendulum-v1 --seeds 3 --steps 100000 --runs cgac ppo sac

Each run name is a hyperparameter file of this repo: ``cgac``, ``ppo``, ``sac`` read ``hyperparams/<name>.yml``,
and other files can be added by name (``ppo_parallel`` reads ``hyperparams/ppo_parallel.yml`` and trains PPO: the
algorithm is the part of the name before ``_``; ``rsl_ppo`` trains rsl_rl's PPO, extra ``rsl_rl``). Models are
built exactly as ``python -m sb3_cgac.train`` builds them. Every (run, seed) pair trains in its own process with
one torch thread and one envpool thread, ``--jobs`` of them at once, so that two runs share a 2-core machine evenly.
Finished pairs are skipped when the command runs again: a long comparison can be split over several calls. When a pair
fails, no other starts, the running ones finish, and the command ends with the failure.

The budget is env steps (``--steps``) or training wall-clock minutes (``--minutes``; evaluation time is not counted,
and the entries' ``n_timesteps`` do not stop a run early, though schedules follow them). Evaluations are
deterministic, on separate envs, every ``--eval-every`` of the budget (a fraction of the steps, or minutes). Outputs
in ``--out``: ``evaluations.csv`` (run, seed, steps, seconds, mean_return, mean_length: the mean episode length,
which tells early terminations from poor behaviour; empty for runs made before it was recorded),
``return_vs_steps.png`` and ``return_vs_time.png`` (mean with a 95% bootstrap band over seeds; the IQM with rliable
from 3 seeds on) and ``summary.md`` (final and best return, steps/s, time to reach a threshold, and the ratios of
those times to PPO's and SAC's). ``--success-key success`` adds each evaluation's success rate (the info key at
each episode's last step, e.g. Adroit's ``success``); ``--metrics reward_tracking_lin_vel ...`` adds a column per
episode statistic of the envpool and gymnasium adapters (their ``episode_info``: mean over the evaluation's episodes)
and its final value to the summary. Beside each pair's evaluations,
``runs/<run>_seed<seed>_train.csv`` holds the latest ``train/*`` values of the model's logger at each evaluation
(CGAC: alpha as ``ent_coef``, ``entropy``, the losses...) and the mean return and length of the training envs' latest
episodes (``rollout_return``, ``rollout_length``; SB3's ``ep_info_buffer``).
"""

import argparse
import json
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from sb3_cgac.threads import configure_thread_spin

COLUMNS = ["run", "seed", "steps", "seconds", "mean_return", "mean_length"]


def run_paths(out: Path, run: str, seed: int) -> tuple[Path, Path, Path]:
    """Evaluations, completion record and log of one (run, seed) pair."""
    # Names built as strings: a run name may hold a dot (``cgac_beta_0.5``), which Path.with_suffix would cut
    stem = f"{run}_seed{seed}"
    return out / "runs" / f"{stem}.csv", out / "runs" / f"{stem}.json", out / "runs" / f"{stem}.log"


def train_stats_path(out: Path, run: str, seed: int) -> Path:
    """The training statistics (the logger's ``train/*`` values) at each evaluation of one (run, seed) pair."""
    return out / "runs" / f"{run}_seed{seed}_train.csv"


def write_csv_atomically(path: Path, text: str) -> None:
    # The parent process reads the evaluations to show progress: it never sees a half-written file
    partial = path.with_suffix(".tmp")
    partial.write_text(text)
    partial.replace(path)


def record_train_stats(
    path: Path,
    rows: list[dict[str, str]],
    logged: dict[str, Any],
    steps: int,
    seconds: float,
    episodes: Iterable[dict[str, Any]] = (),
) -> None:
    """
    Append the latest ``train/*`` values of a model's logger (``logger.name_to_value``) to ``rows`` and write them
    all to ``path``: alpha, entropy, losses... beside each evaluation, to explain a collapse without rerunning (empty
    before the first update, and right after a logger dump for SAC). With ``episodes``, the mean return and length
    of the training envs' latest episodes as well (``rollout_return``, ``rollout_length``): the stochastic policy's
    episodes beside the deterministic evaluations, e.g. whether both end early by termination.

    :param path: The CSV file to (re)write, e.g. ``train_stats_path(out, run, seed)``
    :param rows: The rows recorded so far; the new one is appended in place
    :param logged: The model's ``logger.name_to_value``
    :param steps: Env steps at this evaluation
    :param seconds: Training wall-clock at this evaluation
    :param episodes: The model's ``ep_info_buffer`` (the Monitor infos ``r`` and ``l`` of its latest episodes, and
        the adapters' episode statistics, recorded as ``rollout_<key>``)
    """
    from sb3_cgac.vec_env import episode_metrics  # imports torch, which compare's main process does not load

    stats = {}
    for key, value in logged.items():
        if key.startswith("train/") and isinstance(value, int | float | np.number):
            stats[key.removeprefix("train/")] = f"{float(value):.6g}"
    finished = list(episodes)
    if finished:
        stats["rollout_return"] = f"{np.mean([episode['r'] for episode in finished]):.6g}"
        stats["rollout_length"] = f"{np.mean([episode['l'] for episode in finished]):.6g}"
        for key, value in episode_metrics(finished).items():
            stats[f"rollout_{key}"] = f"{value:.6g}"
    rows.append({"steps": str(steps), "seconds": f"{seconds:.2f}", **stats})
    keys = list(dict.fromkeys(key for row in rows for key in row))
    lines = [",".join(keys)] + [",".join(row.get(key, "") for key in keys) for row in rows]
    write_csv_atomically(path, "\n".join(lines) + "\n")


# --------------------------------------------------------------------------------------------------------------
# One (run, seed) pair, in a worker process
# --------------------------------------------------------------------------------------------------------------


def follow_planned_progress(model: Any, planned_timesteps: int) -> None:
    """
    Under a time budget, let the model's schedules (learning rates, ``LinearSchedule`` decays) follow the progress of
    the entry's planned ``n_timesteps``, as in a zoo run of the entry, clipped at its end; ``learn()`` itself runs
    until the clock stops it. The progress SB3 tracks is otherwise that of ``learn()``'s total.
    """

    def update(num_timesteps: int, total_timesteps: int) -> None:
        model._current_progress_remaining = max(0.0, 1.0 - num_timesteps / planned_timesteps)

    model._update_current_progress_remaining = update


def train_one(args: argparse.Namespace) -> None:
    """Train one (run, seed) pair under the budget, writing its evaluations as it goes."""
    import torch as th
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.evaluation import evaluate_policy
    from stable_baselines3.common.vec_env import sync_envs_normalization

    from sb3_cgac.distributed import init_from_env, leave
    from sb3_cgac.zoo import HYPERPARAMS_DIR, algorithm_of, build_model

    th.set_num_threads(args.threads)
    # Under torchrun (--nproc-per-run) every rank trains on its own envs; rank 0 evaluates and writes, and the budget
    # and the CSVs count the env steps of all ranks
    rank, world_size = init_from_env()
    csv_path, done_path, _ = run_paths(Path(args.out), args.run, args.seed)
    backend_kwargs = {"num_threads": args.threads} if args.backend == "envpool" else None
    with tempfile.TemporaryDirectory() as log_folder:
        model, manager = build_model(
            algorithm_of(args.file),
            args.env,
            seed=args.seed,
            backend=args.backend,
            backend_kwargs=backend_kwargs,
            log_folder=log_folder,
            conf_file=str(Path(args.conf_dir or HYPERPARAMS_DIR) / f"{args.file}.yml"),
            hyperparams=json.loads(args.overrides) if args.overrides else None,
            n_timesteps=args.steps or 0,
            device="cpu",
        )
        eval_env = manager.create_envs(args.eval_envs, eval_env=True) if rank == 0 else None
    rows: list[str] = []
    train_rows: list[dict[str, str]] = []

    class EvaluateWithinBudget(BaseCallback):
        """Evaluates on a schedule and stops at the budget; the budget's clock stops during evaluations."""

        def _on_training_start(self) -> None:
            self.seconds, self.resumed = 0.0, time.perf_counter()
            self.evaluate()

        def clock(self) -> float:
            return self.seconds + time.perf_counter() - self.resumed

        def steps(self) -> int:
            return self.num_timesteps * world_size

        def evaluate(self) -> None:
            self.seconds = self.clock()
            if args.minutes:
                self.next_evaluation = self.seconds + args.eval_every * 60
            else:
                self.next_evaluation = self.steps() + args.eval_every * args.steps
            assert eval_env is not None  # rank 0's
            sync_envs_normalization(self.training_env, eval_env)
            successes: list[bool] = []
            metrics: dict[str, list[float]] = {key: [] for key in args.metrics}

            def record_episode(locals_: dict[str, Any], _globals: dict[str, Any]) -> None:
                # As SB3's EvalCallback records is_success: the info of each episode's last step
                if not locals_["done"]:
                    return
                info = locals_["info"]
                if args.success_key:
                    successes.append(bool(info.get(args.success_key, False)))
                for key in args.metrics:
                    if key in info.get("episode", {}):
                        metrics[key].append(float(info["episode"][key]))

            returns, lengths = evaluate_policy(
                self.model,
                eval_env,
                n_eval_episodes=args.eval_episodes,
                deterministic=True,
                callback=record_episode,
                return_episode_rewards=True,
            )
            values = [args.run, str(args.seed), str(self.steps()), f"{self.seconds:.2f}"]
            values += [f"{np.mean(returns):.3f}", f"{np.mean(lengths):.1f}"]
            values += [f"{np.mean(successes) if successes else 0.0:.3f}"] if args.success_key else []
            values += [f"{np.mean(found):.6g}" if found else "" for found in metrics.values()]
            rows.append(",".join(values) + "\n")
            header = ",".join(COLUMNS + (["success_rate"] if args.success_key else []) + list(args.metrics))
            write_csv_atomically(csv_path, header + "\n" + "".join(rows))
            self.record_train_stats()
            self.resumed = time.perf_counter()

        def record_train_stats(self) -> None:
            path = train_stats_path(Path(args.out), args.run, args.seed)
            logged, episodes = self.model.logger.name_to_value, self.model.ep_info_buffer or ()
            record_train_stats(path, train_rows, logged, self.steps(), self.seconds, episodes)

        def _on_step(self) -> bool:
            if args.minutes and self.clock() >= args.minutes * 60:
                return False
            if args.steps and self.steps() >= args.steps:
                return True  # the step budget's last rollout: the end of training evaluates the final model
            if (self.clock() if args.minutes else self.steps()) >= self.next_evaluation:
                self.evaluate()
            return True

        def _on_training_end(self) -> None:
            self.evaluate()

    evaluator = EvaluateWithinBudget()
    if args.minutes and manager.n_timesteps > 0:
        follow_planned_progress(model, int(manager.n_timesteps))
    # With a time budget, training runs until the clock is out (rank 0's clock), whatever the entry's n_timesteps
    callbacks = [*manager.callbacks, *([evaluator] if rank == 0 else [])]
    model.learn(args.steps // world_size if args.steps else 10**12, callback=callbacks)
    if rank == 0:
        done_path.write_text(json.dumps({"steps": model.num_timesteps * world_size, "seconds": evaluator.seconds}))
    leave()  # under torchrun: every rank ends together


# --------------------------------------------------------------------------------------------------------------
# The comparison: launch the pairs, then summarise them
# --------------------------------------------------------------------------------------------------------------


def launch(args: argparse.Namespace, run: str, seed: int, spec: dict[str, Any]) -> subprocess.Popen:
    command = [sys.executable, "-m", "sb3_cgac.compare"]
    if args.nproc_per_run > 1:  # data-parallel CGAC: torchrun starts the ranks of the pair
        command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", str(args.nproc_per_run)]
        command += ["-m", "sb3_cgac.compare"]
    # (--run-name, not --run: torchrun's parser would take --run for its --run-path)
    command += ["--worker", "--run-name", run, "--file", spec["file"], "--seed", str(seed)]
    command += ["--env", args.env, "--overrides", json.dumps(spec.get("overrides", {}))]
    command += ["--out", args.out, "--backend", args.backend, "--threads", str(args.threads)]
    command += ["--eval-every", str(args.eval_every), "--eval-episodes", str(args.eval_episodes)]
    command += ["--eval-envs", str(args.eval_envs)]
    command += ["--success-key", args.success_key] if args.success_key else []
    command += ["--metrics", *args.metrics] if args.metrics else []
    command += ["--minutes", str(args.minutes)] if args.minutes else ["--steps", str(args.steps)]
    if args.conf_dir:
        command += ["--conf-dir", args.conf_dir]
    with run_paths(Path(args.out), run, seed)[2].open("w") as log:  # the run keeps its own copy of the handle
        return subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)


def progress_of(out: Path, run: str, seed: int, minutes: bool) -> float:
    """Budget used so far by a running pair (seconds or steps), from its latest evaluation."""
    csv_path = run_paths(out, run, seed)[0]
    if not csv_path.exists():
        return 0.0
    last = csv_path.read_text().strip().splitlines()[-1].split(",")
    try:
        return float(last[3] if minutes else last[2])
    except (IndexError, ValueError):  # the header only
        return 0.0


def describe_exit(returncode: int) -> str:
    """How a pair's process ended, in words: a negative return code is the signal that killed it."""
    if returncode >= 0:
        return f"exit code {returncode}"
    try:
        name = signal.Signals(-returncode).name
    except ValueError:
        name = f"signal {-returncode}"
    if -returncode == signal.SIGKILL:
        # envpool's ports of MuJoCo Playground's tasks hold 40-90 MB per env: two runs of a few hundred envs fill 24 GiB
        return f"killed by {name}, most often the kernel's out-of-memory killer: fewer envs or fewer --jobs"
    return f"killed by {name}"


def run_comparison(args: argparse.Namespace, runs: dict[str, dict[str, Any]], references: tuple[str, ...]) -> None:
    """Train every (run, seed) pair not finished yet, ``args.jobs`` at a time, then write the outputs."""
    from tqdm import tqdm

    out = Path(args.out)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    pairs = [(run, seed) for run in runs for seed in range(args.first_seed, args.first_seed + args.seeds)]
    pending = [pair for pair in pairs if not run_paths(out, *pair)[1].exists()]
    print(f"{len(pairs) - len(pending)} of {len(pairs)} (run, seed) pairs already done; training {len(pending)}.")
    budget = args.minutes * 60 if args.minutes else args.steps
    running: dict[tuple[str, int], subprocess.Popen] = {}
    finished = 0
    quiet = not sys.stderr.isatty()
    bar_args = dict(unit="s" if args.minutes else "step", unit_scale=True, mininterval=60 if quiet else 0.1)
    failures: list[str] = []
    # After a failure no new pair starts and the running ones finish (their work is kept, as make does); if this
    # process itself stops (Ctrl-C), the pairs it started stop with it instead of running on unseen
    try:
        with tqdm(total=len(pending) * budget, **bar_args) as bar:
            while running or (pending and not failures):
                while pending and not failures and len(running) < args.jobs:
                    run, seed = pending.pop(0)
                    running[(run, seed)] = launch(args, run, seed, runs[run])
                time.sleep(2)
                for (run, seed), process in list(running.items()):
                    if process.poll() is None:
                        continue
                    del running[(run, seed)]
                    if process.returncode != 0:
                        failure = f"{run} seed {seed} failed ({describe_exit(process.returncode)})"
                        failures.append(f"{failure}:\n{run_paths(out, run, seed)[2].read_text()[-3000:]}")
                        waiting = f"; waiting for {len(running)} running pair(s), starting no other" if running else ""
                        print(f"{failure}{waiting}.", flush=True)
                        bar.total = (finished + len(running)) * budget  # what is left to train: the running pairs
                        continue
                    finished += 1
                used = finished * budget + sum(min(progress_of(out, *pair, bool(args.minutes)), budget) for pair in running)
                bar.update(used - bar.n)
                bar.set_postfix_str(", ".join(f"{run} s{seed}" for run, seed in running), refresh=False)
    finally:
        for process in running.values():
            process.terminate()
        for process in running.values():
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
    if failures:
        raise RuntimeError("\n".join(failures))
    summarise(out, list(runs), args.first_seed + args.seeds, args.threshold, references)


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


def first_reach(frame: Any, threshold: float, column: str) -> float:
    reached = frame[frame["mean_return"] >= threshold]
    return float(reached[column].min()) if len(reached) else float("inf")


def summarise(
    out: Path, runs: list[str], seeds: int, threshold: float | None, references: tuple[str, ...] = ("ppo", "sac")
) -> str:
    """
    Write evaluations.csv, the two plots and summary.md; return the markdown table.

    :param references: Runs whose time to threshold the others are compared with; the threshold defaults to the
        best final return of the first of them
    """
    results, completed = load_results(out, runs, seeds)
    results.sort_values(["run", "seed", "steps"]).to_csv(out / "evaluations.csv", index=False)
    plot(results, runs, "steps", "env steps", 1.0, out / "return_vs_steps.png")
    plot(results, runs, "seconds", "training wall-clock (minutes)", 1 / 60, out / "return_vs_time.png")

    finals = {run: results[results["run"] == run].sort_values("steps").groupby("seed")["mean_return"].last() for run in runs}
    threshold_source = "given"
    if threshold is None:
        # A partial comparison (e.g. `--runs cgac` first) has no reference run yet: take the best final of all runs
        with_results = [run for run in runs if len(finals[run]) > 0]  # load_results found at least one
        if references[0] in with_results:
            threshold_source, sources = f"best of {references[0]}'s final returns", [references[0]]
        else:
            threshold_source, sources = f"best final return of any run; no {references[0]} run yet", with_results
        threshold = float(max(finals[run].max() for run in sources))
    stats: dict[str, dict[str, float]] = {}
    # The --metrics columns: every column after the fixed ones
    metric_columns = [column for column in results.columns if column not in (*COLUMNS, "success_rate")]
    for run in runs:
        # The evaluation before training is left out: an untrained policy can score well (a motionless Ant
        # collects its healthy reward for 1000 steps) and would count as reaching the threshold at 0 s
        frames = [frame[frame["steps"] > 0] for _, frame in results[results["run"] == run].groupby("seed")]
        times = [first_reach(frame, threshold, "seconds") for frame in frames]
        steps = [first_reach(frame, threshold, "steps") for frame in frames]
        done = [completed[(run, seed)] for seed in range(seeds) if (run, seed) in completed]
        stats[run] = {
            "seeds": len(frames),
            "final": float(finals[run].mean()),
            "final_std": float(finals[run].std(ddof=0)),
            "worst": float(finals[run].min()),
            "best": float(np.mean([frame["mean_return"].max() for frame in frames])),
            "sps": float(np.mean([d["steps"] / d["seconds"] for d in done])),
            "reached": int(np.isfinite(times).sum()),
            # Median over seeds, a seed that never reaches the threshold counting as infinitely slow
            "time": float(np.median(times)),
            "steps": float(np.median(steps)),
        }
        if "success_rate" in results:
            # Runs evaluated without --success-key have no rate
            last = results[results["run"] == run].sort_values("steps").groupby("seed")["success_rate"].last()
            stats[run]["success"] = float(last.mean())
        for key in metric_columns:
            last = results[results["run"] == run].sort_values("steps").groupby("seed")[key].last()
            stats[run][f"metric {key}"] = float(last.mean())

    def ratio(run: str, reference: str) -> str:
        if reference not in stats or run == reference:
            return "-"
        mine, theirs = stats[run]["time"], stats[reference]["time"]
        if not np.isfinite(mine):
            return "never"
        if not np.isfinite(theirs):
            return "< 1 (ref. never)"
        return f"{mine / theirs:.2f}x" if theirs > 0 else "-"

    shown = [reference for reference in references if reference in stats]
    with_success = "success_rate" in results
    lines = [
        f"Threshold: {threshold:.1f} ({threshold_source}). "
        "Time and steps to threshold are medians over seeds of the training wall-clock and env steps at the first "
        "evaluation at or above it (so they are only as fine as the evaluation interval); final and best return: "
        "mean over seeds of the last and best evaluation (+/- std over seeds); worst final: the lowest last evaluation "
        "of any seed. The evaluation before training counts "
        "in neither the best return nor the threshold. Ratios below 1 mean faster than the reference.",
        "",
        "| run | seeds | final return | worst final | best return | steps/s | time to threshold | steps to threshold |"
        + "".join(f" time vs {reference} |" for reference in shown)
        + (" final success rate |" if with_success else "")
        + "".join(f" final {key} |" for key in metric_columns),
        "| --- | --- | --- | --- | --- | --- | --- | --- |" + " --- |" * (len(shown) + with_success + len(metric_columns)),
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
            + "".join(f" {ratio(run, reference)} |" for reference in shown)
            + (f" {s['success']:.2f} |" if with_success else "")
            + "".join(f" {s[f'metric {key}']:.4g} |" for key in metric_columns)
        )
    table = "\n".join(lines)
    (out / "summary.md").write_text(table + "\n")
    print(table)
    return table


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", required=True, help="env id (the YAML entries of this id are used)")
    parser.add_argument("--runs", nargs="+", default=["cgac", "ppo", "sac"], help="hyperparameter files by name")
    parser.add_argument("--seeds", type=int, default=3, help="seeds 0 .. seeds-1 of every run (with --first-seed: see there)")
    parser.add_argument(
        "--first-seed",
        type=int,
        default=0,
        help="train seeds first-seed .. first-seed + seeds - 1 only (the summary: every finished seed up to there)",
    )
    budget = parser.add_mutually_exclusive_group(required=True)
    budget.add_argument("--steps", type=int, help="budget of env steps per run")
    budget.add_argument("--minutes", type=float, help="budget of training wall-clock minutes per run")
    parser.add_argument("--eval-every", type=float, default=None, help="fraction of --steps, or minutes (default: 1/20)")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--eval-envs", type=int, default=5)
    parser.add_argument("--success-key", default=None, help="info key at each evaluation episode's end: adds a success rate")
    parser.add_argument(
        "--metrics",
        nargs="+",
        default=[],
        help="episode statistics of the envpool/gymnasium adapters (their episode_info, e.g. reward_tracking_lin_vel) "
        "recorded at each evaluation (mean over its episodes) and in the summary",
    )
    parser.add_argument("--threshold", type=float, default=None, help="return threshold (default: best PPO final return)")
    parser.add_argument("--backend", default="dummy", help="vec-env backend of every run (dummy, envpool, ...)")
    parser.add_argument("--jobs", type=int, default=1, help="runs trained at once")
    parser.add_argument("--threads", type=int, default=1, help="torch (and envpool) threads per run (per rank)")
    parser.add_argument(
        "--nproc-per-run",
        type=int,
        default=1,
        help="ranks of data-parallel CGAC per run, started by torchrun (sb3_cgac.distributed); each has --threads threads",
    )
    parser.add_argument("--conf-dir", default=None, help="folder of the YAML files (default: this package's hyperparams)")
    parser.add_argument("--out", default=None, help="output folder (default: results/<env>)")
    parser.add_argument("--summary-only", action="store_true", help="only rebuild the CSV, plots and table")
    # Internal: one (run, seed) pair
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--run-name", dest="run", help=argparse.SUPPRESS)
    parser.add_argument("--file", help=argparse.SUPPRESS)
    parser.add_argument("--seed", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--overrides", default="", help=argparse.SUPPRESS)
    return parser


def check_run_files(parser: argparse.ArgumentParser, conf_dir: str | None, files: list[str], env: str) -> None:
    """Stop with one line when a run names no hyperparameter file, or its file has no entry for the env."""
    import importlib.resources

    import yaml

    folder = Path(conf_dir) if conf_dir else Path(str(importlib.resources.files("sb3_cgac.hyperparams")))
    available = sorted(path.stem for path in folder.glob("*.yml"))
    for name in files:
        path = folder / f"{name}.yml"
        if not path.is_file():
            message = f"run {name!r}: no file {path}; the runs of {folder} are {', '.join(available) or 'none'}"
            parser.exit(2, f"{parser.prog}: error: {message}\n")
        entries = yaml.safe_load(path.read_text()) or {}
        if env not in entries:
            message = f"run {name!r}: {path} has no entry for {env!r}; its entries are {', '.join(map(str, entries))}"
            parser.exit(2, f"{parser.prog}: error: {message}\n")


def main(
    runs: dict[str, dict[str, Any]] | None = None, argv: list[str] | None = None, references: tuple[str, ...] = ("ppo", "sac")
) -> None:
    """
    :param runs: Run name -> ``{"file": YAML file name, "overrides": {hyperparameter: value}}`` (``experiments/ablations.py``
        passes its variants this way); default: ``--runs``, each its own file without overrides
    :param argv: Command-line arguments
    :param references: Runs the others are compared with (see ``summarise``)
    """
    configure_thread_spin()  # the workers inherit the setting; torch is not loaded yet in this process
    parser = build_parser()
    args = parser.parse_args(argv)
    args.out = args.out or f"results/{args.env}"
    if args.eval_every is None:
        args.eval_every = args.minutes / 20 if args.minutes else 0.05
    if args.worker:
        train_one(args)
        return
    runs = runs if runs is not None else {run: {"file": run} for run in args.runs}
    if not args.summary_only:
        check_run_files(parser, args.conf_dir, [run["file"] for run in runs.values()], args.env)
    if args.summary_only:
        summarise(Path(args.out), list(runs), args.first_seed + args.seeds, args.threshold, references)
    else:
        run_comparison(args, runs, references)


if __name__ == "__main__":
    main()
