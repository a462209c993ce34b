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


def test_export_go1(tmp_path):
    """Trains Go1 for a few hundred steps, exports the asymmetric actor to ONNX and replays it in the env (``state`` only)."""
    pytest.importorskip("onnxruntime")
    envpool = pytest.importorskip("envpool")
    if "Go1JoystickFlatTerrain-v1" not in envpool.list_all_envs():
        pytest.skip("this envpool has no MuJoCo Playground tasks (envpool >= 1.2.5)")
    args = ("--timesteps", "1024", "--n-envs", "16", "--replay-steps", "50", "--output", "go1.onnx")
    stdout = run_example("export_go1.py", *args, cwd=tmp_path)
    assert (tmp_path / "go1.onnx").exists()
    assert "ONNX inputs: ['state']" in stdout
    gap = float(stdout.split("largest gap to predict(): ")[1].split()[0])
    assert gap < 1e-5, stdout


def test_distributed(tmp_path):
    """The example under torchrun: two ranks on gloo, rank 0 saves."""
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2"]
    script = str(EXAMPLES / "distributed.py")
    args = ["--env", "Pendulum-v1", "--timesteps", "4096", "--n-envs", "16", "--output", str(tmp_path / "model")]
    run = subprocess.run([*command, script, *args], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "2 rank(s) trained 4096 steps in all" in run.stdout
    assert (tmp_path / "model.zip").exists()
