"""benchmarks/throughput.py runs end to end on a tiny budget and prints a complete table (timings are not asserted)."""

import pathlib
import subprocess
import sys

import pytest

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


def test_collection_profile_tiny_budget():
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "collection_profile.py"), "--env", "Hopper-v5", "--n-envs", "4",
         "--calls", "20", "--seconds", "0.2", "--chunk", "0.05"],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    lines = result.stdout.splitlines()
    assert sum("torch thread" in line and line.strip().split()[-1].replace(".", "").isdigit() for line in lines) == 8
    assert sum("5 ms idle" in line for line in lines) == 2
    assert sum("small torch ops" in line and line.strip().split()[-1].replace(".", "").isdigit() for line in lines) == 2
    for name in ("raw", "bare loop", "CGAC collection", "CGAC collection, bfloat16 forward"):
        assert any(line.strip().startswith(f"{name}: ") and "% of raw)" in line for line in lines), name
        env_step = [line for line in lines if line.strip().startswith(f"env step in {name}: ")]
        assert len(env_step) == 1 and float(env_step[0].split()[-1]) > 0, name
    part3 = lines[next(i for i, line in enumerate(lines) if line.startswith("3. envpool's own API")) :]
    for name in ("raw, uniform actions", "raw, the actor's actions", "sync: step, forward", "in step: send all, recv halves",
                 "async", "raw, uniform actions, pinned threads", "sync: step, forward, pinned threads"):  # fmt: skip
        assert any(line.strip().startswith(f"{name}: ") and "% of raw)" in line for line in part3), name
    assert any("step counts spread over" in line for line in part3)
    assert any(line.strip().startswith("pinned threads (thread_affinity_offset=") for line in part3)
