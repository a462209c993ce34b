"""
``python -m sb3_cgac.compare``: CGAC against SB3's PPO and SAC (or any runs of this repo's YAML files) on one env, on
the same machine with the same budget; the command, its options and its outputs are documented in
``sb3_cgac.compare.cli`` (``python -m sb3_cgac.compare --help``).

The package: ``runs`` trains one (run, seed) pair in a worker process (``evaluation``: its callback), ``files`` holds
the pairs' files, ``pairs`` launches and follows the pairs,
``report`` writes the outputs, ``cli`` is the command line.
"""

from sb3_cgac.compare.cli import build_parser, check_run_files, main
from sb3_cgac.compare.files import (
    COLUMNS,
    finished_pairs,
    record_train_stats,
    run_paths,
    train_stats_path,
    write_csv_atomically,
)
from sb3_cgac.compare.pairs import run_comparison
from sb3_cgac.compare.report import load_results, new_axis, plot, save_figure, summarise
from sb3_cgac.compare.runs import follow_planned_progress, train_one

__all__ = [
    "COLUMNS",
    "build_parser",
    "check_run_files",
    "finished_pairs",
    "follow_planned_progress",
    "load_results",
    "main",
    "new_axis",
    "plot",
    "record_train_stats",
    "run_comparison",
    "run_paths",
    "save_figure",
    "summarise",
    "train_one",
    "train_stats_path",
    "write_csv_atomically",
]
