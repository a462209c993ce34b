"""One (run, seed) pair of a comparison, trained in its own process."""

import argparse
import json
import tempfile
from pathlib import Path
from typing import Any

from sb3_cgac.compare.files import run_paths


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

    from sb3_cgac.common.distributed import init_from_env, leave
    from sb3_cgac.compare.evaluation import EvaluateWithinBudget
    from sb3_cgac.zoo import HYPERPARAMS_DIR, algorithm_of, build_model

    th.set_num_threads(args.threads)
    # Under torchrun (--nproc-per-run) every rank trains on its own envs; rank 0 evaluates and writes, and the budget
    # and the CSVs count the env steps of all ranks
    rank, world_size = init_from_env()
    done_path = run_paths(Path(args.out), args.run, args.seed)[1]
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
        evaluator = (
            EvaluateWithinBudget(args, manager.create_envs(args.eval_envs, eval_env=True), world_size) if rank == 0 else None
        )
    if args.minutes and manager.n_timesteps > 0:
        follow_planned_progress(model, int(manager.n_timesteps))
    # With a time budget, training runs until the clock is out (rank 0's clock), whatever the entry's n_timesteps
    callbacks = [*manager.callbacks, *([evaluator] if evaluator is not None else [])]
    model.learn(args.steps // world_size if args.steps else 10**12, callback=callbacks)
    if evaluator is not None:
        done_path.write_text(json.dumps({"steps": model.num_timesteps * world_size, "seconds": evaluator.seconds}))
    leave()  # under torchrun: every rank ends together
