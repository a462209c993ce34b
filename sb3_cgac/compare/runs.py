"""One (run, seed) pair of a comparison, trained in its own process: its files, evaluations and training statistics."""

import argparse
import json
import tempfile
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

COLUMNS = ["run", "seed", "steps", "seconds", "mean_return", "mean_length"]


def run_paths(out: Path, run: str, seed: int) -> tuple[Path, Path, Path]:
    """Evaluations, completion record and log of one (run, seed) pair."""
    # Names built as strings: a run name may hold a dot (``cgac_beta_0.5``), which Path.with_suffix would cut
    stem = f"{run}_seed{seed}"
    return out / "runs" / f"{stem}.csv", out / "runs" / f"{stem}.json", out / "runs" / f"{stem}.log"


def finished_pairs(out: Path) -> list[tuple[str, int]]:
    """Every (run, seed) pair with a completion record in ``out/runs``, whichever comparison trained it."""
    pairs = []
    for path in (out / "runs").glob("*_seed*.json"):
        run, _, seed = path.name[: -len(".json")].rpartition("_seed")
        if seed.isdigit():
            pairs.append((run, int(seed)))
    return sorted(pairs)


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
