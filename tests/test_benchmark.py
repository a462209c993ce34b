"""benchmarks/throughput.py runs end to end on a tiny budget and prints a complete table (timings are not asserted)."""

import os
import pathlib
import subprocess
import sys
import warnings
from types import SimpleNamespace

import pytest
import torch as th

pytest.importorskip("envpool")
pytest.importorskip("rl_zoo3")

ROOT = pathlib.Path(__file__).parents[1]


def test_throughput_table_tiny_budget(tmp_path):
    out = tmp_path / "throughput.md"
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "throughput.py"), "--envs", "Hopper-v5", "--n-envs", "4",
         "--backends", "dummy", "envpool", "--seconds", "0.2", "--chunk", "0.05", "--e2e-seconds", "0.3",
         "--output", str(out)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    rows = [line for line in out.read_text().splitlines() if line.startswith("| Hopper-v5")]
    assert [row.split(" | ")[2] for row in rows[:2]] == ["DummyVecEnv", "envpool"]
    for row in rows[:2]:
        cells = [cell.strip() for cell in row.strip("|").split("|")]
        raw, collect = float(cells[3].replace(",", "")), float(cells[4].split(" (")[0].replace(",", ""))
        assert raw > 0 and collect > 0
        assert cells[6].count("%") == 4  # env / infer / update / else
        assert 1.0 <= float(cells[7]) <= 1.2  # buffer bytes within 1.2x of the raw transition bytes
    for row, algo in zip(rows[2:], ("PPO", "SAC"), strict=True):
        cells = [cell.strip() for cell in row.strip("|").split("|")]
        assert cells[1].startswith(f"SB3 {algo} (zoo settings") and float(cells[5].replace(",", "")) > 0


def table_rows(stdout: str, first_cell: str) -> list[list[str]]:
    return [
        [cell.strip() for cell in line.strip("|").split("|")]
        for line in stdout.splitlines()
        if line.startswith(f"| {first_cell}")
    ]


@pytest.mark.parametrize("baseline_path, baseline_name", [("default", "CGAC at HEAD"), ("bf16", "CGAC at HEAD bf16")])
def test_update_benchmark_tiny_budget(baseline_path, baseline_name):
    command = [sys.executable, str(ROOT / "benchmarks" / "updates.py"), "--batch-sizes", "64", "--critics", "16,16",
               "--actor", "16", "--paths", "default", "bf16", "--rounds", "1", "--chunk", "0.05",
               "--warmup", "1", "--threads", "1", "--baseline", "HEAD", "--baseline-path", baseline_path]  # fmt: skip
    result = subprocess.run(command, capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert result.returncode == 0, result.stderr[-3000:]
    rows = table_rows(result.stdout, "64")
    gemms = ["GEMMs of CGAC's step", "GEMMs of SAC's step", "GEMMs of CGAC's step, bf16"]
    assert [row[2] for row in rows] == ["CGAC default", "CGAC bf16", "SB3 SAC", *gemms, baseline_name]
    for row in rows:
        assert float(row[3]) > 0 and float(row[7]) > 0  # ms per step, GFLOP/s
    assert rows[2][4] == "1.00" and rows[0][5] == "1.00" and rows[-1][6] == "1.00"  # each ratio's reference


def test_step_gemms_match_the_flop_count():
    # The products timed as "what the hardware allows" are those of the GFLOP/s column, less the first layers' input
    # gradients, which that count includes and autograd skips (the data need none)
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import updates
    finally:
        sys.path.pop(0)
    batch, actor, critic = 64, [32, 16], [24, 8]
    obs, act = updates.OBS_DIM, updates.ACTION_DIM
    first_actor, first_critic = 2 * batch * obs * actor[0], 2 * batch * (obs + act) * critic[0]
    for algo, skipped in (("cgac", 2 * first_critic + first_actor), ("sac", 2 * first_critic + first_actor)):
        flop = sum(2 * m * k * n for m, k, n in updates.step_gemms(batch, actor, critic, 2, algo))
        assert flop == pytest.approx(updates.matmul_gflop(batch, actor, critic, 2, algo) * 1e9 - skipped)
    # SAC's step has CGAC's products plus its targets and the critics' weight gradients in the actor update
    cgac, sac = (updates.step_gemms(batch, actor, critic, 2, algo) for algo in ("cgac", "sac"))
    assert len(sac) > len(cgac) and all(sac.count(gemm) >= cgac.count(gemm) for gemm in cgac)


def test_update_benchmark_end_to_end():
    command = [sys.executable, str(ROOT / "benchmarks" / "updates.py"), "--e2e", "Pendulum-v1", "--paths", "default",
               "--rounds", "1", "--chunk", "0.05", "--warmup", "1", "--threads", "1"]  # fmt: skip
    result = subprocess.run(command, capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert result.returncode == 0, result.stderr[-3000:]
    rows = table_rows(result.stdout, "Pendulum-v1")
    assert len(rows) == 1 and float(rows[0][2].replace(",", "")) > 0


def test_data_parallel_table(tmp_path):
    # benchmarks/data_parallel.py's table from two compare folders: the ratio of steps/s, and each run's return at the
    # env steps both reached (interpolated between evaluations)
    columns = "run,seed,steps,seconds,mean_return,mean_length\n"
    (tmp_path / "2-ranks-1-thread").mkdir()
    (tmp_path / "1-process-2-threads").mkdir()
    ranks = "cgac,0,0,0,0,1000\ncgac,0,200000,50,100,1000\ncgac,0,400000,100,300,1000\n"
    (tmp_path / "2-ranks-1-thread" / "evaluations.csv").write_text(columns + ranks)
    single = "cgac,0,0,0,0,1000\ncgac,0,300000,100,250,1000\n"
    (tmp_path / "1-process-2-threads" / "evaluations.csv").write_text(columns + single)
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "data_parallel.py"), "--out", str(tmp_path), "--minutes", "1.6667",
         "--table-only"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    assert "| 0 | 2 ranks x 1 thread | 400,000 | 4,000 | 300 | 200 (300,000) |" in result.stdout
    assert "| 0 | 1 process x 2 threads | 300,000 | 3,000 | 250 | 250 (300,000) |" in result.stdout
    assert "steps/s ratio (ranks / one process), per seed: 1.33; mean 1.33" in result.stdout
    assert (tmp_path / "summary.md").read_text().strip() == result.stdout.strip()


def test_ops_per_iteration_table():
    command = [sys.executable, str(ROOT / "benchmarks" / "ops_per_iteration.py"), "--n-envs", "16", "--iterations", "2"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    rows = {
        row[0].split(" (")[0]: [float(cell.replace(",", "")) for cell in row[1:]] for row in table_rows(result.stdout, "the ")
    }
    counts = {phase: cells[0] for phase, cells in rows.items()}
    assert list(counts) == ["the collection", "the Q-GAE targets", "the minibatches", "the updates"]
    assert all(count > 0 for count in counts.values())
    assert counts["the updates"] > counts["the minibatches"]  # eager updates on the CPU: hundreds of ops each
    # The window's writes on a CPU device go through NumPy: part of the collection, none of the minibatches
    assert 0 < rows["the collection"][1] < counts["the collection"] and rows["the minibatches"][1] == 0


def test_playground_compile_table():
    pytest.importorskip("mujoco_playground")
    command = [sys.executable, str(ROOT / "benchmarks" / "playground_compile.py"), "--task", "CartpoleBalance", "--envs", "4"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    seconds = {row[0]: float(row[1]) for row in table_rows(result.stdout, "") if row[0] not in ("call", "---")}
    assert list(seconds) == ["build", "reset", "first step", "second step", "partial reset", "step after it"]
    assert all(value >= 0 for value in seconds.values())


def test_gpu_benchmark_tiny_budget_on_the_cpu(tmp_path):
    # benchmarks/gpu.sh is run once when a GPU is lent, for minutes: its whole path (the wrapper, the Playground adapter,
    # CGAC and rsl_rl's PPO, the table) runs here on JAX's CPU backend at 8 envs, so that it does not first fail there
    pytest.importorskip("mujoco_playground")
    pytest.importorskip("rsl_rl")
    command = ["bash", str(ROOT / "benchmarks" / "gpu.sh"), str(tmp_path), "--task", "CartpoleBalance", "--envs", "8",
               "--learn-envs", "8", "--seconds", "0.5", "--learn-seconds", "2"]  # fmt: skip
    environment = {**os.environ, "PYTHON": sys.executable}
    result = subprocess.run(command, capture_output=True, text=True, timeout=600, cwd=ROOT, env=environment)
    assert result.returncode == 0 and "exit 0" in result.stdout, (result.stdout + result.stderr)[-3000:]
    table = (tmp_path / "table.md").read_text()
    assert "Task: CartpoleBalance (MuJoCo Playground, impl=jax)" in table
    (row,) = table_rows(table, "8 ")
    assert float(row[1].replace(",", "")) > 0 and float(row[2].replace(",", "")) > 0  # raw and CGAC steps/s
    assert row[4] == "-"  # CGAC with eager updates beside the graphs: CUDA only
    shares = [float(share.strip(" %")) for share in row[5].split("/")]  # simulator / collection / updates / else
    assert len(shares) == 4 and min(shares[:3]) > 0 and sum(shares) == pytest.approx(100, abs=2)
    learning = {row[0]: row for row in table_rows(table, "cgac") + table_rows(table, "rsl_ppo")}
    assert set(learning) == {"cgac", "rsl_ppo"}
    assert all(int(row[2].replace(",", "")) > 0 for row in learning.values())  # env steps trained
    assert (tmp_path / "machine.txt").exists() and (tmp_path / "results.json").exists()


def test_gpu_benchmark_keeps_going_after_a_failed_measurement(tmp_path, monkeypatch):
    # On a lent GPU the script runs once: a measurement that fails (out of memory at 16,384 envs, say) is listed in
    # the table, the ones before and after it are kept, and the exit code says that something failed
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import gpu_playground

    def measured(results):
        results["raw"][8] = 1000.0

    def fails(results):
        raise RuntimeError("CUDA out of memory")

    def measured_after(results):
        results["learning"]["rsl_ppo"] = {"steps_per_s": 500.0, "steps": 4096, "return": 1.5}

    phases = [("raw 8", measured), ("cgac 16", fails), ("learning rsl_ppo", measured_after)]
    monkeypatch.setattr(gpu_playground, "phases", lambda args: phases)
    monkeypatch.setattr(gpu_playground, "machine", lambda device: "a test machine")
    monkeypatch.setattr(sys, "argv", ["gpu_playground.py", "--out", str(tmp_path), "--envs", "8", "16", "--learn-envs", "8"])
    assert gpu_playground.main() == 1
    table = (tmp_path / "table.md").read_text()
    (row,) = table_rows(table, "8 ")
    assert row[1] == "1,000" and row[2] == "0"  # raw measured, CGAC not
    assert table_rows(table, "rsl_ppo") == [["rsl_ppo", "500", "4,096", "1.5"]]
    assert "- cgac 16: RuntimeError: CUDA out of memory" in table


def test_gpu_benchmark_trains_cgac_again_eagerly_when_its_cuda_graphs_fail(monkeypatch):
    # A failure of the CUDA graphs at their capture must not leave the comparison of returns without CGAC
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import gpu_playground

    trained_with = []

    def learn_and_evaluate(algo, args, cuda_graphs):
        trained_with.append(cuda_graphs)
        if cuda_graphs:
            raise RuntimeError("CUDA error: operation not permitted when stream is capturing")
        return SimpleNamespace(num_timesteps=4096), 1000.0, 2.5

    monkeypatch.setattr(gpu_playground, "learn_and_evaluate", learn_and_evaluate)
    monkeypatch.setattr(gpu_playground, "CGAC", SimpleNamespace)  # the stub model counts as CGAC's
    monkeypatch.setattr(gpu_playground, "phase_split", lambda model, seconds: {"env": 1.0})

    def learning_cgac():
        args = SimpleNamespace(learn_envs=8, envs=[8], cuda_graphs=True, split_seconds=1.0)
        (measure,) = [measure for name, measure in gpu_playground.phases(args) if name == "learning cgac"]
        return measure

    measure = learning_cgac()
    results = {"errors": [], **{key: {} for key in ("raw", "cgac", "cgac_eager", "split", "learning")}}
    measure(results)
    assert trained_with == [True, False]
    assert results["learning"]["cgac"] == {"steps_per_s": 1000.0, "steps": 4096, "return": 2.5}
    assert results["cgac_eager"] == {8: 1000.0} and results["cgac"] == {}  # the rate is the eager updates'
    (error,) = results["errors"]
    assert error.startswith("learning cgac with CUDA graphs: RuntimeError") and "trained again with eager" in error
    # A failure after RETRY_WITHIN seconds is not retried
    trained_with.clear()
    monkeypatch.setattr(gpu_playground, "RETRY_WITHIN", -1.0)
    with pytest.raises(RuntimeError, match="capturing"):
        learning_cgac()(results)
    assert trained_with == [True]


def test_gpu_benchmark_counts_host_syncs(monkeypatch):
    # On CUDA, the synchronising calls torch makes in CGAC's iterations are counted by place and written in the table
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import gpu_playground

    modes = []
    monkeypatch.setattr(th.cuda, "set_sync_debug_mode", modes.append)

    class Model:
        n_steps, n_envs = 1, 8

        def learn(self, total_timesteps, reset_num_timesteps):
            assert total_timesteps == 4 * 8 and not reset_num_timesteps
            for _ in range(4):  # one read of the statistics per iteration
                warnings.warn("called a synchronizing CUDA operation", UserWarning)

    syncs = gpu_playground.host_syncs(Model(), iterations=4)
    assert modes == ["warn", "default"]
    assert syncs["iterations"] == 4 and syncs["per_iteration"] == 1.0 and list(syncs["places"].values()) == [4]
    args = SimpleNamespace(envs=[8], learn_envs=8, cuda_graphs=True, impl="jax", learn_seconds=3.0)
    results = {"machine": "a test machine", "task": "CartpoleBalance", "errors": [], "syncs": syncs}
    results.update({key: {} for key in ("raw", "cgac", "cgac_eager", "split", "learning")})
    table = gpu_playground.table(results, args)
    assert (
        "Host syncs per CGAC iteration (torch.cuda.set_sync_debug_mode, 4 iterations at 8 envs after the learning run): 1.0"
        in table
    )
    assert "test_benchmark.py:" in table  # where the syncs were made


def test_gpu_benchmark_reports_the_entry_critics_beside_the_default(monkeypatch):
    # The LeapCube entry's critics and window are timed at --learn-envs and reported as a ratio to the defaults' rate there
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import gpu_playground

    args = SimpleNamespace(envs=[8], learn_envs=8, cuda_graphs=True, impl="jax", learn_seconds=3.0)
    assert "cgac 8 critic options" in [name for name, _ in gpu_playground.phases(args)]
    results = {"machine": "a test machine", "task": "CartpoleBalance", "errors": []}
    results.update({key: {} for key in ("raw", "cgac", "cgac_eager", "split", "learning")})
    results["cgac"][8], results["cgac_critic"] = 1000.0, {8: 400.0}
    table = gpu_playground.table(results, args)
    assert "window (256 steps, lambda 0.5) at 8 envs, CUDA graphs of the updates: 400 steps/s (0.40x the defaults')." in table
    # ... and that row's model is built with them
    built: dict = {}
    stub_env = SimpleNamespace(observation_space=gpu_playground.spaces.Box(-1.0, 1.0, (3,)))
    monkeypatch.setattr(gpu_playground, "playground", lambda args, n_envs, seed: stub_env)
    monkeypatch.setattr(gpu_playground, "CGAC", lambda policy, env, **kwargs: built.update(kwargs))
    gpu_playground.build("cgac", 8, SimpleNamespace(device="cpu"), critic_options=True)
    assert (built["buffer_window"], built["gae_lambda"], built["policy_kwargs"]["n_bins"]) == (256, 0.5, 101)
