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
episodes (``rollout_return``, ``rollout_length``; SB3's ``ep_info_buffer``); the summary adds the last
``rollout_return`` of each seed (mean over seeds) as the final training return. The outputs cover every finished
pair in ``--out/runs``, the named runs first: adding a run or a seed to a folder (or ``--summary-only``) keeps its
earlier runs in ``evaluations.csv`` and ``summary.md``.
"""

import argparse
from pathlib import Path
from typing import Any

from sb3_cgac.compare.pairs import run_comparison
from sb3_cgac.compare.report import summarise
from sb3_cgac.compare.runs import train_one
from sb3_cgac.threads import configure_thread_spin


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m sb3_cgac.compare", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
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
        help="ranks of data-parallel CGAC per run, started by torchrun (sb3_cgac.common.distributed), each with --threads "
        "threads",
    )
    parser.add_argument("--conf-dir", default=None, help="folder of the YAML files (default: this package's hyperparams)")
    parser.add_argument("--out", default=None, help="output folder (default: results/<env>)")
    parser.add_argument(
        "--summary-only", action="store_true", help="only rebuild the CSV, plots and table (every finished pair in --out)"
    )
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
