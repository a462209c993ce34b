"""The example programs run end to end on tiny budgets (the quickstart runs in CI's first set-up command)."""

import pathlib
import subprocess
import sys

import pytest

EXAMPLES = pathlib.Path(__file__).parents[1] / "examples"


def run_example(name: str, *args: str, cwd: pathlib.Path) -> str:
    result = subprocess.run(
        [sys.executable, str(EXAMPLES / name), *args], capture_output=True, text=True, timeout=600, cwd=cwd
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return result.stdout


def test_many_envs_envpool(tmp_path):
    pytest.importorskip("envpool")
    stdout = run_example("many_envs_envpool.py", "--n-envs", "16", "--timesteps", "1024", cwd=tmp_path)
    assert "Mean evaluation return after 1024 steps" in stdout


def test_zoo_usage(tmp_path):
    pytest.importorskip("rl_zoo3")
    stdout = run_example("zoo_usage.py", "--env", "Pendulum-v1", "--backend", "dummy", "--timesteps", "640", cwd=tmp_path)
    assert "Pendulum-v1: CGAC with 64 envs" in stdout
    assert (tmp_path / "cgac_zoo" / "model.zip").exists()
