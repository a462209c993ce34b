"""
CGAC vs SB3 PPO vs SB3 SAC on Pendulum-v1, 3 seeds, 100k env steps each, two runs at a time
(``pip install -e ".[zoo]"``): a short version of the comparisons in the README.

    python examples/compare.py

The command-line tool behind it has every option (wall-clock budgets, envpool, more runs, resuming):
``python -m sb3_cgac.compare --help``. Outputs in ``results/Pendulum-v1-example``: ``evaluations.csv``, two plots and
``summary.md``.
"""

from pathlib import Path

from sb3_cgac.compare import main

if __name__ == "__main__":
    out = Path("results") / "Pendulum-v1-example"
    main(argv=["--env", "Pendulum-v1", "--runs", "cgac", "ppo", "sac", "--seeds", "3", "--steps", "100000", "--jobs", "2",
               "--threshold", "-200", "--out", str(out)])  # fmt: skip
    print((out / "summary.md").read_text())
