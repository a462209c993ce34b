"""experiments/evaluation_noise.py: evaluations against the training returns logged beside them."""

import pandas as pd
import pytest
from evaluation_noise import main  # experiments/ is on sys.path (conftest.py)


def write_folder(folder, evaluations: list[float], training: list[float]) -> None:
    (folder / "runs").mkdir(parents=True)
    steps = [1000 * i for i in range(len(evaluations))]
    pd.DataFrame(dict(run="cgac", seed=0, steps=steps, seconds=steps, mean_return=evaluations, mean_length=10.0)).to_csv(
        folder / "evaluations.csv", index=False
    )
    # The per-run file as compare writes it: the statistics at each evaluation, none before the first update
    pd.DataFrame(dict(steps=steps, seconds=steps, rollout_return=[None, *training[1:]])).to_csv(
        folder / "runs" / "cgac_seed0_train.csv", index=False
    )
    # The completion record compare writes when the run ends
    (folder / "runs" / "cgac_seed0.json").write_text('{"steps": 4000, "seconds": 4000}')


def test_evaluation_noise_table_and_differences(tmp_path, capsys):
    write_folder(tmp_path / "a", [0, 50, 120, 80, 100], [0, 60, 100, 100, 90])
    main([str(tmp_path / "a"), "--last", "3", "--write"])
    out = capsys.readouterr().out
    # Last 3 pairs: evaluations 120, 80, 100 against 100, 100, 90: final 100 = 0.83x of 120, training 90 = 0.90x of
    # 100; differences 20, -20, 10: mean 3.3, std 17.0
    assert "| a | cgac | 0 | 100 (0.83x) | 90 (0.90x) |" in out
    assert "cgac (all runs): evaluation - training return +3.3 +/- 17.0 (1 seeds, 3 pairs)" in out
    # --write keeps the training returns once the per-run files are gone
    (tmp_path / "a" / "runs" / "cgac_seed0_train.csv").unlink()
    main([str(tmp_path / "a"), "--last", "3"])
    assert "| a | cgac | 0 | 100 (0.83x) | 90 (0.90x) |" in capsys.readouterr().out


def test_evaluation_noise_last_is_checked(tmp_path):
    with pytest.raises(ValueError, match="--last"):
        main([str(tmp_path), "--last", "0"])


def test_evaluation_noise_leaves_out_unfinished_runs(tmp_path, capsys):
    write_folder(tmp_path / "a", [0, 50, 120, 80, 100], [0, 60, 100, 100, 90])
    # A run still training: its statistics so far, no completion record
    pd.DataFrame(dict(steps=[0, 1000], seconds=[0, 1000], rollout_return=[None, 5.0])).to_csv(
        tmp_path / "a" / "runs" / "cgac_window_seed0_train.csv", index=False
    )
    main([str(tmp_path / "a"), "--write"])
    written = pd.read_csv(tmp_path / "a" / "training_returns.csv")
    assert set(written["run"]) == {"cgac"} and len(written) == 5
