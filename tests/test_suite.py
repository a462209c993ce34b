"""benchmarks/suite.py: the compare commands it runs, and its table and figure from a task folder's evaluations."""

import argparse
import importlib.util
import pathlib

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).parents[1]
spec = importlib.util.spec_from_file_location("suite", ROOT / "benchmarks" / "suite.py")
assert spec is not None and spec.loader is not None
suite = importlib.util.module_from_spec(spec)
spec.loader.exec_module(suite)


def test_compare_arguments_follow_the_suite_table():
    args = argparse.Namespace(seeds=3, first_seed=0, eval_fraction=0.05, jobs=2, out="out", conf_dir="conf")
    panda = suite.TASKS["MuJoCoPlayground/PandaPickCube-v1"]
    argv = suite.compare_argv(panda, ["defaults", "rsl_ppo", "ppo_parallel"], args)
    assert argv[argv.index("--minutes") + 1] == "20" and argv[argv.index("--eval-every") + 1] == "1.0"
    assert argv[argv.index("--backend") + 1] == "envpool" and argv[argv.index("--out") + 1] == str(
        pathlib.Path("out/PandaPickCube-v1")
    )
    assert "--metrics" in argv and argv[-2:] == ["--conf-dir", "conf"]
    assert suite.parse_runs(["defaults=cgac", "ppo"]) == {"defaults": {"file": "cgac"}, "ppo": {"file": "ppo"}}
    assert {task.env for task in suite.SUITE if task.minutes == 10} == {"HalfCheetah-v5", "Hopper-v5", "Walker2d-v5"}


def write_evaluations(folder: pathlib.Path, curves: dict[str, list[list[float]]]) -> None:
    folder.mkdir(parents=True)
    lines = ["run,seed,steps,seconds,mean_return,mean_length"]
    for run, seeds in curves.items():
        for seed, returns in enumerate(seeds):
            lines += [f"{run},{seed},{step * 1000},{step},{value},100" for step, value in enumerate(returns)]
    (folder / "evaluations.csv").write_text("\n".join(lines) + "\n")


def test_table_normalises_to_the_better_baseline(tmp_path):
    pytest.importorskip("pandas")
    write_evaluations(
        tmp_path / "Hopper-v5",
        {
            # untrained 0 everywhere; finals 300 / 200 / 250: IQM 250; seed 1 ends at 200 after 400 in the second half
            "defaults": [[0, 100, 200, 300], [0, 300, 400, 200], [0, 150, 250, 250]],
            "ppo": [[0, 50, 100, 100], [0, 60, 100, 100], [0, 70, 100, 100]],
            "sac": [[0, 100, 200, 200], [0, 100, 200, 200], [0, 100, 200, 200]],
        },
    )
    table = suite.summarise_suite(tmp_path, [suite.TASKS["Hopper-v5"]], ["defaults"])
    row = next(line for line in table.splitlines() if line.startswith("| Hopper-v5"))
    cells = [cell.strip() for cell in row.strip("|").split("|")]
    assert cells[1] == "ppo 100, sac 200"
    assert cells[2:] == ["250 (3)", "1.25", "0.50"]
    assert (tmp_path / "suite.md").read_text().strip() == table and (tmp_path / "suite.png").stat().st_size > 0


def test_negative_returns_normalise_from_the_untrained_score():
    # Pendulum-like: untrained -1200, better baseline -200; a run at -700 is half way
    assert suite.normalised(-700.0, -200.0, -1200.0) == pytest.approx(0.5)
    assert suite.late_ratio(np.array([-1200.0, -150.0, -300.0]), np.array([0, 1, 2])) == pytest.approx(0.5)
    assert suite.iqm(np.array([99.0, 130.0, 104.0])) == 104.0
