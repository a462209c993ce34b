"""experiments/scaling.py: time to a fraction of the best return against the action dims; the compare summary it reads."""

import numpy as np
import pytest

pytest.importorskip("pandas")
pytest.importorskip("matplotlib")

import pandas as pd
from scaling import main, time_to_fraction  # experiments/ is on sys.path (conftest.py)


def evaluations(run: str, seed: int, returns: list[float]) -> list[dict]:
    return [
        dict(run=run, seed=seed, steps=1000 * i, seconds=60.0 * i, mean_return=value) for i, value in enumerate(returns)
    ]  # fmt: skip


def test_time_to_fraction():
    frame = pd.DataFrame(evaluations("cgac", 0, [-1000, -600, -200, -300]))
    # 80% of the improvement from -1000 to -200 is -360: first reached at the third evaluation
    assert time_to_fraction(frame, 0.8) == 120.0
    assert time_to_fraction(frame, 0.5) == 60.0
    # The evaluation before training does not count, and a seed that never improves never reaches it
    assert time_to_fraction(pd.DataFrame(evaluations("cgac", 0, [5, 3, 1])), 0.8) == float("inf")


def test_scaling_table_and_plot(tmp_path):
    for env_id, (cgac, ppo) in {"Pendulum-v1": ([0, 5, 10], [0, 2, 10]), "myoLegWalk-v0": ([0, 10, 9], [0, 0, 1])}.items():
        folder = tmp_path / env_id
        folder.mkdir()
        rows = evaluations("cgac", 0, cgac) + evaluations("cgac", 1, cgac) + evaluations("ppo", 0, ppo)
        pd.DataFrame(rows).to_csv(folder / "evaluations.csv", index=False)
    table = main([str(tmp_path / "Pendulum-v1"), f"{tmp_path / 'myoLegWalk-v0'}:80", "--out", str(tmp_path / "scaling")])
    assert (tmp_path / "scaling.png").exists() and (tmp_path / "scaling.md").read_text().strip() == table
    lines = table.splitlines()
    assert lines[4] == "| Pendulum-v1 | 1 | 2.0 (2 seeds) | 2.0 (1 seed) |"
    assert lines[5] == "| myoLegWalk-v0 | 80 | 1.0 (2 seeds) | 2.0 (1 seed) |"
    # An env that is not installed needs its dimensions in the argument
    (tmp_path / "NotInstalled-v0").mkdir()
    (tmp_path / "NotInstalled-v0" / "evaluations.csv").write_text((tmp_path / "Pendulum-v1" / "evaluations.csv").read_text())
    with pytest.raises(ValueError, match="pass its action dimensions"):
        main([str(tmp_path / "NotInstalled-v0"), "--out", str(tmp_path / "other")])


def test_joined_folders(tmp_path):
    # A new CGAC entry (a variant folder with CGAC only) beside the PPO runs of an older comparison of the same env
    for name, rows in {
        "Pendulum-v1-new-entry": evaluations("cgac", 0, [0, 10, 10]),
        "Pendulum-v1": evaluations("cgac", 0, [0, 0, 10]) + evaluations("ppo", 0, [0, 0, 0, 10]),
    }.items():
        (tmp_path / name).mkdir()
        pd.DataFrame(rows).to_csv(tmp_path / name / "evaluations.csv", index=False)
    joined = f"{tmp_path / 'Pendulum-v1-new-entry'}+{tmp_path / 'Pendulum-v1'}"
    table = main([joined, "--out", str(tmp_path / "scaling")])
    # CGAC from the first folder (1 minute, not the older folder's 2), PPO from the second
    assert table.splitlines()[4] == "| Pendulum-v1 | 1 | 1.0 (1 seed) | 3.0 (1 seed) |"
    (tmp_path / "Hopper-v5").mkdir()
    with pytest.raises(ValueError, match="different envs"):
        main([f"{tmp_path / 'Pendulum-v1'}+{tmp_path / 'Hopper-v5'}", "--out", str(tmp_path / "other")])
    with pytest.raises(ValueError, match="not named after an env id"):
        main([str(tmp_path / "scaling"), "--out", str(tmp_path / "other")])


def test_series_of_differently_named_runs(tmp_path):
    # Entries tuned in variant folders under their own run names, plotted as one series with the older entries' cgac
    for name, rows in {
        "Pendulum-v1": evaluations("cgac", 0, [0, 0, 10]) + evaluations("cgac_new", 0, [0, 10, 10]),
        "Hopper-v5": evaluations("cgac", 0, [0, 0, 0, 10]) + evaluations("ppo", 0, [0, 10]),
    }.items():
        (tmp_path / name).mkdir()
        pd.DataFrame(rows).to_csv(tmp_path / name / "evaluations.csv", index=False)
    folders = [str(tmp_path / "Pendulum-v1"), f"{tmp_path / 'Hopper-v5'}:3"]
    table = main([*folders, "--runs", "cgac=cgac_new,cgac", "ppo", "--out", str(tmp_path / "scaling")])
    lines = table.splitlines()
    assert lines[2] == "| env | action dims | cgac | ppo |"
    # The first run name a folder has is taken, and named where it is not the series
    assert lines[4] == "| Pendulum-v1 | 1 | 1.0 (1 seed, cgac_new) | - |"
    assert lines[5] == "| Hopper-v5 | 3 | 3.0 (1 seed) | 1.0 (1 seed) |"
    for runs, message in ([["cgac", "cgac=cgac_new"], "twice"], [["cgac="], "write a run name"], [["=x"], "write a run name"]):
        with pytest.raises(ValueError, match=message):
            main([*folders, "--runs", *runs, "--out", str(tmp_path / "other")])


def test_fraction_is_checked(tmp_path):
    with pytest.raises(ValueError, match="--fraction"):
        main([str(tmp_path), "--fraction", "1.5"])
    assert np.isfinite(time_to_fraction(pd.DataFrame(evaluations("ppo", 0, [0, 1])), 1.0))


def test_compare_summary_without_reference_run(tmp_path):
    # A partial comparison (CGAC first, PPO later) still gets a table: its threshold is the best final of its runs
    from sb3_cgac.compare import run_paths, summarise

    (tmp_path / "runs").mkdir()
    for seed, returns in enumerate([[0, 5, 10], [0, 20, 15]]):
        csv_path, done_path, _ = run_paths(tmp_path, "cgac", seed)
        pd.DataFrame(evaluations("cgac", seed, returns)).to_csv(csv_path, index=False)
        done_path.write_text('{"steps": 2000, "seconds": 120.0}')
    table = summarise(tmp_path, ["cgac"], 2, None)
    assert "Threshold: 15.0 (best final return of any run; no ppo run yet)" in table
    assert "| cgac | 2 | 12 +/- 2 |" in table


def test_compare_summary_final_training_return(tmp_path):
    # The training envs' latest episodes at the last evaluation beside the (noisy) final evaluation; "-" where a
    # run has no training statistics
    from sb3_cgac.compare import run_paths, summarise, train_stats_path

    (tmp_path / "runs").mkdir()
    for run in ("cgac", "ppo"):
        for seed, returns in enumerate([[0, 5, 10], [0, 20, 15]]):
            csv_path, done_path, _ = run_paths(tmp_path, run, seed)
            pd.DataFrame(evaluations(run, seed, returns)).to_csv(csv_path, index=False)
            done_path.write_text('{"steps": 2000, "seconds": 120.0}')
    for seed, last in enumerate([100.0, 120.0]):
        training = pd.DataFrame({"steps": [0, 1000, 2000], "rollout_return": [np.nan, 50.0, last]})
        training.to_csv(train_stats_path(tmp_path, "cgac", seed), index=False)
    table = summarise(tmp_path, ["cgac", "ppo"], 2, None)
    assert "final training return |" in table.splitlines()[2]
    assert table.splitlines()[4].endswith("| 110 |") and table.splitlines()[5].endswith("| - |")


def test_compare_summary_keeps_the_folders_other_runs(tmp_path):
    # Adding a run (or a seed) to a folder, or --summary-only with one run, must not drop the folder's earlier runs
    # from evaluations.csv and summary.md: they are often the only files kept of a comparison
    from sb3_cgac.compare import finished_pairs, run_paths, summarise

    (tmp_path / "runs").mkdir()
    for run, seeds in (("ppo", 3), ("cgac_beta_0.5", 1), ("cgac", 2)):
        for seed in range(seeds):
            csv_path, done_path, _ = run_paths(tmp_path, run, seed)
            pd.DataFrame(evaluations(run, seed, [0, 5, 10 + seed])).to_csv(csv_path, index=False)
            done_path.write_text('{"steps": 2000, "seconds": 120.0}')
    run_paths(tmp_path, "sac", 0)[0].write_text("unfinished: no completion record")
    assert finished_pairs(tmp_path) == [("cgac", 0), ("cgac", 1), ("cgac_beta_0.5", 0), ("ppo", 0), ("ppo", 1), ("ppo", 2)]
    table = summarise(tmp_path, ["cgac_beta_0.5"], 1, None)
    rows = [line.split(" | ")[:2] for line in table.splitlines()[4:]]
    assert rows == [["| cgac_beta_0.5", "1"], ["| cgac", "2"], ["| ppo", "3"]]
    written = pd.read_csv(tmp_path / "evaluations.csv")
    assert sorted(set(zip(written["run"], written["seed"], strict=True))) == finished_pairs(tmp_path)


def test_run_names_with_a_dot(tmp_path):
    # A hyperparameter file named after a value (cgac_beta_0.5.yml): every seed keeps files of its own
    from sb3_cgac.compare import run_paths, train_stats_path

    paths = [
        (*run_paths(tmp_path, "cgac_beta_0.5", seed), train_stats_path(tmp_path, "cgac_beta_0.5", seed)) for seed in (0, 1)
    ]
    assert [path.name for path in paths[1]] == [
        "cgac_beta_0.5_seed1.csv", "cgac_beta_0.5_seed1.json", "cgac_beta_0.5_seed1.log", "cgac_beta_0.5_seed1_train.csv"
    ]  # fmt: skip
    assert len({path for pair in paths for path in pair}) == 8


def test_output_stem_with_a_dot(tmp_path):
    folder = tmp_path / "Pendulum-v1"
    folder.mkdir()
    pd.DataFrame(evaluations("cgac", 0, [0, 5, 10])).to_csv(folder / "evaluations.csv", index=False)
    table = main([str(folder), "--out", str(tmp_path / "scaling_v0.2")])
    assert (tmp_path / "scaling_v0.2.png").exists() and (tmp_path / "scaling_v0.2.md").read_text().strip() == table
