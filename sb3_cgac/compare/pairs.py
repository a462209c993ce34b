"""A comparison's pairs: launched as processes, ``--jobs`` at a time, skipped when already finished, then summarised."""

import argparse
import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from sb3_cgac.compare.files import run_paths
from sb3_cgac.compare.report import summarise


def launch(args: argparse.Namespace, run: str, seed: int, spec: dict[str, Any]) -> subprocess.Popen:
    command = [sys.executable, "-m", "sb3_cgac.compare"]
    if args.nproc_per_run > 1:  # data-parallel CGAC: torchrun starts the ranks of the pair
        command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", str(args.nproc_per_run)]
        command += ["-m", "sb3_cgac.compare"]
    # (--run-name, not --run: torchrun's parser would take --run for its --run-path)
    command += ["--worker", "--run-name", run, "--file", spec["file"], "--seed", str(seed)]
    command += ["--env", args.env, "--overrides", json.dumps(spec.get("overrides", {}))]
    command += ["--out", args.out, "--backend", args.backend, "--threads", str(args.threads)]
    command += ["--eval-every", str(args.eval_every), "--eval-episodes", str(args.eval_episodes)]
    command += ["--eval-envs", str(args.eval_envs)]
    command += ["--success-key", args.success_key] if args.success_key else []
    command += ["--metrics", *args.metrics] if args.metrics else []
    command += ["--minutes", str(args.minutes)] if args.minutes else ["--steps", str(args.steps)]
    if args.conf_dir:
        command += ["--conf-dir", args.conf_dir]
    with run_paths(Path(args.out), run, seed)[2].open("w") as log:  # the run keeps its own copy of the handle
        return subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)


def progress_of(out: Path, run: str, seed: int, minutes: bool) -> float:
    """Budget used so far by a running pair (seconds or steps), from its latest evaluation."""
    csv_path = run_paths(out, run, seed)[0]
    if not csv_path.exists():
        return 0.0
    last = csv_path.read_text().strip().splitlines()[-1].split(",")
    try:
        return float(last[3] if minutes else last[2])
    except (IndexError, ValueError):  # the header only
        return 0.0


def describe_exit(returncode: int) -> str:
    """How a pair's process ended, in words: a negative return code is the signal that killed it."""
    if returncode >= 0:
        return f"exit code {returncode}"
    try:
        name = signal.Signals(-returncode).name
    except ValueError:
        name = f"signal {-returncode}"
    if -returncode == signal.SIGKILL:
        # envpool's ports of MuJoCo Playground's tasks hold 40-90 MB per env: two runs of a few hundred envs fill 24 GiB
        return f"killed by {name}, most often the kernel's out-of-memory killer: fewer envs or fewer --jobs"
    return f"killed by {name}"


def run_comparison(args: argparse.Namespace, runs: dict[str, dict[str, Any]], references: tuple[str, ...]) -> None:
    """Train every (run, seed) pair not finished yet, ``args.jobs`` at a time, then write the outputs."""
    from tqdm import tqdm

    out = Path(args.out)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    pairs = [(run, seed) for run in runs for seed in range(args.first_seed, args.first_seed + args.seeds)]
    pending = [pair for pair in pairs if not run_paths(out, *pair)[1].exists()]
    print(f"{len(pairs) - len(pending)} of {len(pairs)} (run, seed) pairs already done; training {len(pending)}.")
    budget = args.minutes * 60 if args.minutes else args.steps
    running: dict[tuple[str, int], subprocess.Popen] = {}
    finished = 0
    quiet = not sys.stderr.isatty()
    bar_args = dict(unit="s" if args.minutes else "step", unit_scale=True, mininterval=60 if quiet else 0.1)
    failures: list[str] = []
    # After a failure no new pair starts and the running ones finish (their work is kept, as make does); if this
    # process itself stops (Ctrl-C), the pairs it started stop with it instead of running on unseen
    try:
        with tqdm(total=len(pending) * budget, **bar_args) as bar:
            while running or (pending and not failures):
                while pending and not failures and len(running) < args.jobs:
                    run, seed = pending.pop(0)
                    running[(run, seed)] = launch(args, run, seed, runs[run])
                time.sleep(2)
                for (run, seed), process in list(running.items()):
                    if process.poll() is None:
                        continue
                    del running[(run, seed)]
                    if process.returncode != 0:
                        failure = f"{run} seed {seed} failed ({describe_exit(process.returncode)})"
                        failures.append(f"{failure}:\n{run_paths(out, run, seed)[2].read_text()[-3000:]}")
                        waiting = f"; waiting for {len(running)} running pair(s), starting no other" if running else ""
                        print(f"{failure}{waiting}.", flush=True)
                        bar.total = (finished + len(running)) * budget  # what is left to train: the running pairs
                        continue
                    finished += 1
                used = finished * budget + sum(min(progress_of(out, *pair, bool(args.minutes)), budget) for pair in running)
                bar.update(used - bar.n)
                bar.set_postfix_str(", ".join(f"{run} s{seed}" for run, seed in running), refresh=False)
    finally:
        for process in running.values():
            process.terminate()
        for process in running.values():
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
    if failures:
        raise RuntimeError("\n".join(failures))
    summarise(out, list(runs), args.first_seed + args.seeds, args.threshold, references)
