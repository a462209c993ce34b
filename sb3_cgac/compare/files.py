"""The files of a comparison's (run, seed) pairs: their paths, evaluations and training statistics."""

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
