"""benchmarks/defaults_at_scale.py trains its (env count, seed) pairs and writes them in sb3_cgac.compare's layout."""

import json
import pathlib
import subprocess
import sys

import numpy as np

SCRIPT = pathlib.Path(__file__).parents[1] / "benchmarks" / "defaults_at_scale.py"


def test_defaults_at_scale_tiny_budget(tmp_path):
    command = [sys.executable, str(SCRIPT), "--n-envs", "16", "32", "--seeds", "1", "--first-seed", "3", "--steps", "640",
               "--eval-every", "320", "--eval-episodes", "1", "--eval-envs", "1", "--device", "cpu", "--out", str(tmp_path),
               "--overrides", '{"tau": 0.25, "batch_size": 64}', "--name", "fast-tau"]  # fmt: skip
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    for n_envs in (16, 32):
        runs = tmp_path / f"Pendulum-v1-defaults-{n_envs}-envs-cpu-fast-tau" / "runs"
        rows = np.genfromtxt(runs / "cgac_seed3.csv", delimiter=",", names=True, dtype=None, encoding=None)
        assert list(rows.dtype.names) == ["run", "seed", "steps", "seconds", "mean_return", "mean_length"]
        assert rows["steps"][0] == 0 and rows["steps"][-1] >= 640  # before training, on the grid, and at the end
        assert np.all(rows["mean_return"] < 0)  # Pendulum-v1's returns
        done = json.loads((runs / "cgac_seed3.json").read_text())
        assert done["steps"] == rows["steps"][-1]
        stats = np.genfromtxt(runs / "cgac_seed3_train.csv", delimiter=",", names=True)
        assert stats["n_updates"][-1] > 0  # the small batch let the updates start within the budget
        assert stats["tau"][-1] == 0.25  # the override reached the model
        assert not (runs / "cgac_seed0.csv").exists()  # --first-seed 3: seed 3 only
