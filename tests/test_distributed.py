"""Data-parallel CGAC over torch.distributed: two ranks on gloo, started by torchrun (tests/distributed_worker.py)."""

import json
import pathlib
import subprocess
import sys
import time

import numpy as np
import pytest
import torch.distributed as dist
from stable_baselines3.common.env_util import make_vec_env

from sb3_cgac import CGAC

if not dist.is_available():
    pytest.skip("this torch build has no torch.distributed", allow_module_level=True)

WORKER = pathlib.Path(__file__).with_name("distributed_worker.py")


def torchrun(check: str, folder: pathlib.Path, timeout: float = 300) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2", str(WORKER)]
    return subprocess.run([*command, check, str(folder)], capture_output=True, text=True, timeout=timeout)


def results(folder: pathlib.Path) -> list[dict]:
    return [json.loads((folder / f"rank{rank}.json").read_text()) for rank in range(2)]


@pytest.mark.parametrize("variant", ["", "-critic-options"])
def test_two_ranks_train_identical_parameters_and_save(tmp_path, variant):
    run = torchrun("train" + variant, tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    ranks = results(tmp_path)
    assert [rank["world_size"] for rank in ranks] == [2, 2]
    # Identical to the last bit: parameters, averaged copies, normaliser statistics and alpha
    assert all(rank["identical"] for rank in ranks)
    # ...from different envs (each rank its own seed), whose observations both went into the statistics
    assert ranks[0]["envs_differ"]
    assert ranks[0]["normalizer_count"] == pytest.approx(2 * 8 * (1 + 60), abs=1e-3)
    assert [rank["num_timesteps"] for rank in ranks] == [8 * 60, 8 * 60]
    assert ranks[0]["return_count"] == pytest.approx(2 * 8 * 60, abs=1e-3)
    assert ranks[0]["reward_scale"] == ranks[1]["reward_scale"]
    assert ranks[0]["loaded_predicts"]
    # Rank 0 saved; the model loads and predicts in a single process
    model = CGAC.load(tmp_path / "model", env=make_vec_env("Pendulum-v1", n_envs=8))
    actions, _ = model.predict(np.zeros((8, 3), np.float32), deterministic=True)
    assert actions.shape == (8, 1) and np.all(np.isfinite(actions))
    model.learn(8 * 4)  # trains on alone


@pytest.mark.parametrize("variant", ["", "-critic-options"])
def test_averaged_gradients_equal_one_process_with_both_minibatches(tmp_path, variant):
    run = torchrun("gradients" + variant, tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    for rank in results(tmp_path):
        assert rank["minibatches_differ"]
        assert rank["max_gap"] <= 1e-5 * rank["scale"] + 1e-7, rank


def test_vec_normalize_statistics_merged(tmp_path):
    run = torchrun("vecnormalize", tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    for rank in results(tmp_path):
        assert rank["identical"]
        # Both ranks' observations: 8 envs x (20 steps + the reset) each
        assert rank["count"] == pytest.approx(2 * 8 * 21, abs=1e-3)


def test_zoo_trainer_and_compare_under_torchrun(tmp_path):
    """torchrun around the zoo's trainer (rank 0 saves where asked), and compare's --nproc-per-run."""
    pytest.importorskip("rl_zoo3")
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2", "-m", "sb3_cgac.train"]
    logs = tmp_path / "logs"
    command += ["--algo", "cgac", "--env", "Pendulum-v1", "-n", "2048", "-f", str(logs), "--seed", "1"]
    run = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    saved = list(logs.glob("cgac/Pendulum-v1_*/Pendulum-v1.zip"))
    assert len(saved) == 1  # rank 0's; rank 1 wrote into a temporary folder
    model = CGAC.load(saved[0])
    assert model.num_timesteps == 1024  # n_timesteps counts both ranks' steps
    out = tmp_path / "cmp"
    command = [sys.executable, "-m", "sb3_cgac.compare", "--env", "Pendulum-v1", "--runs", "cgac", "--seeds", "1"]
    command += ["--steps", "2048", "--eval-every", "0.5", "--eval-episodes", "2", "--eval-envs", "2", "--nproc-per-run", "2"]
    run = subprocess.run([*command, "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    steps = [int(line.split(",")[2]) for line in (out / "runs" / "cgac_seed0.csv").read_text().splitlines()[1:]]
    assert steps[0] == 0 and steps[-1] == 2048  # the env steps of both ranks
    assert json.loads((out / "runs" / "cgac_seed0.json").read_text())["steps"] == 2048


def test_a_failing_rank_ends_the_run(tmp_path):
    start = time.perf_counter()
    run = torchrun("fail", tmp_path, timeout=240)
    assert run.returncode != 0
    assert "rank 1 fails on purpose" in run.stdout + run.stderr
    assert time.perf_counter() - start < 200  # ended, not hung until a collective's timeout
    assert not (tmp_path / "rank0.json").exists()


def test_single_process_is_unchanged():
    """Without a process group the model runs as before: no DataParallel, the seed as given."""
    model = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4), batch_size=32, seed=5)
    model.learn(4 * 8)
    assert model._parallel is None
    again = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=4), batch_size=32, seed=5)
    again.learn(4 * 8)
    for a, b in zip(model.policy.parameters(), again.policy.parameters(), strict=True):
        assert (a == b).all()
