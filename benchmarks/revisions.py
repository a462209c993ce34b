"""
Training throughput of this checkout (or a second revision) against a git revision, side by side in one run.

    python benchmarks/revisions.py HEAD~1                # this checkout against HEAD~1: every case, 8 rounds
    python benchmarks/revisions.py 85f7146 973f1ca      # one commit against its parent
    python benchmarks/revisions.py v0.2.0 --cases quickstart --rounds 4 --output revisions.md
    python benchmarks/revisions.py HEAD --cases halfcheetah --conf candidate.yml   # a YAML's entry against the entry

Each revision trains in its own process (the revision's ``sb3_cgac`` first on ``PYTHONPATH``, extracted with ``git
archive``; the YAML entries of this checkout's ``hyperparams/``), and the processes take turns: one chunk of training
of one, then the same chunk of the other, so that the machine's speed drift hits both alike and only one trains at a
time. ``--conf`` and ``--old-conf`` build the HalfCheetah-v5 cases from another YAML file's entry on the new and the
old side (the same revision on both sides compares two settings). A round's ratio is the new side's steps/s (this
checkout, or the second revision) over the old side's in that round; the table gives the mean steps/s over the rounds
and the median and range of the rounds' ratios. Run it on a quiet machine; timings are printed, never asserted.

Cases (CPU, the library's default threads):
- ``halfcheetah``: the HalfCheetah-v5 entry of hyperparams/cgac.yml (128 envs, DummyVecEnv), built as the zoo builds it;
- ``quickstart``: examples/quickstart.py's model (Pendulum-v1, 64 envs, [64, 64] networks, the defaults);
- ``collect``: the HalfCheetah-v5 entry's collection alone (the averaged actor's actions, the env steps and the
  window's writes; 80-95% of the end-to-end time on a CPU is updates, which hides a change in collection).
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from timing import machine  # benchmarks/timing.py

ROOT = Path(__file__).resolve().parents[1]

# Runs in each revision's process: builds the case's model, fills its window, then trains one chunk per line of stdin
# and answers with the steps and seconds of that chunk
WORKER = """
import json, sys, tempfile, time

import torch as th

out, sys.stdout = sys.stdout, sys.stderr  # stdout answers the parent; what the library prints goes to stderr
case, chunk, conf = sys.argv[1], int(sys.argv[2]), sys.argv[3] or None
if case in ("halfcheetah", "collect"):
    from sb3_cgac.zoo import build_model

    model, _ = build_model("cgac", "HalfCheetah-v5", seed=0, log_folder=tempfile.mkdtemp(), conf_file=conf, device="cpu")
else:
    from sb3_cgac import CGAC
    from sb3_cgac.vec_env import make_vec_env

    env = make_vec_env("Pendulum-v1", n_envs=64, seed=0)
    model = CGAC("MlpPolicy", env, gamma=0.98, policy_kwargs=dict(net_arch=[64, 64]), seed=0, device="cpu")
env = model.get_env()
n_envs = env.num_envs
model.learn(model.buffer_window * n_envs, log_interval=10**9)  # updates start once the window holds a minibatch
if case == "collect":  # collection alone: the averaged actor's actions, the env steps and the window's writes
    _, callback = model._setup_learn(10**12, reset_num_timesteps=False)
    callback.on_training_start(locals(), globals())
print(json.dumps({"threads": th.get_num_threads()}), file=out, flush=True)
for _ in sys.stdin:
    start_steps, start = model.num_timesteps, time.perf_counter()
    if case == "collect":
        model.collect_rollouts(env, callback, model.rollout_buffer, n_rollout_steps=chunk)
    else:
        model.learn(chunk * n_envs, reset_num_timesteps=False, log_interval=10**9)
    answer = {"steps": model.num_timesteps - start_steps, "seconds": time.perf_counter() - start}
    print(json.dumps(answer), file=out, flush=True)
"""

CASES = {
    "halfcheetah": "HalfCheetah-v5 entry (128 envs), end to end",
    "quickstart": "quickstart (Pendulum-v1, 64 envs), end to end",
    "collect": "HalfCheetah-v5 entry (128 envs), collection alone",
}


def extract(revision: str, folder: Path) -> str:
    """The revision's tree in ``folder``; returns its commit."""
    commit = subprocess.run(["git", "rev-parse", "--short", revision], cwd=ROOT, check=True, capture_output=True, text=True)
    archive = subprocess.run(["git", "archive", revision], cwd=ROOT, check=True, capture_output=True)
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive.stdout, check=True)
    return commit.stdout.strip()


def start_worker(source: Path, case: str, chunk: int, conf: str) -> tuple[subprocess.Popen, int]:
    """
    A process that trains ``case`` with the ``sb3_cgac`` of ``source`` (and the YAML file ``conf``, if not empty),
    and its number of torch threads.
    """
    env = {**os.environ, "PYTHONPATH": str(source)}
    command = [sys.executable, "-c", WORKER, case, str(chunk), conf]
    process = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
    assert process.stdout is not None
    return process, json.loads(process.stdout.readline())["threads"]


def run_chunk(process: subprocess.Popen) -> float:
    assert process.stdin is not None and process.stdout is not None
    process.stdin.write("go\n")
    process.stdin.flush()
    answer = json.loads(process.stdout.readline())
    return answer["steps"] / answer["seconds"]


def compare(case: str, sources: dict[str, tuple[Path, str]], chunk: int, rounds: int) -> tuple[dict[str, list[float]], int]:
    """
    Steps/s of each source (a tree and a YAML file or "") in each round, the sources taking turns (their order
    alternates from round to round), and the workers' number of torch threads.
    """
    started = {name: start_worker(source, case, chunk, conf) for name, (source, conf) in sources.items()}
    workers = {name: process for name, (process, _) in started.items()}
    rates: dict[str, list[float]] = {name: [] for name in sources}
    try:
        for _ in workers:  # one chunk each to warm up
            for process in workers.values():
                run_chunk(process)
        names = list(workers)
        for round_index in range(rounds):
            for name in names if round_index % 2 == 0 else names[::-1]:
                rates[name].append(run_chunk(workers[name]))
    finally:
        for process in workers.values():
            process.kill()
    return rates, max(threads for _, threads in started.values())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("revision", help="the git revision to compare with (e.g. HEAD~1)")
    parser.add_argument("new", nargs="?", help="a second revision, the new side (default: this checkout as it is)")
    parser.add_argument("--cases", nargs="+", choices=list(CASES), default=list(CASES))
    parser.add_argument("--rounds", type=int, default=8)
    parser.add_argument("--chunk", type=int, default=128, help="steps of every env per chunk")
    parser.add_argument("--conf", default="", help="YAML file of the new side's HalfCheetah-v5 entry")
    parser.add_argument("--old-conf", default="", help="YAML file of the old side's HalfCheetah-v5 entry")
    parser.add_argument("--output", help="also write the table to this file")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as old_folder, tempfile.TemporaryDirectory() as new_folder:
        commit = extract(args.revision, Path(old_folder))
        new = extract(args.new, Path(new_folder)) if args.new else "this checkout"
        new += f" ({Path(args.conf).stem})" if args.conf else ""
        commit += f" ({Path(args.old_conf).stem})" if args.old_conf else ""
        confs = [str(Path(conf).resolve()) if conf else "" for conf in (args.conf, args.old_conf)]
        sources = {new: (Path(new_folder) if args.new else ROOT, confs[0]), commit: (Path(old_folder), confs[1])}
        lines = [
            f"| case | {new} (steps/s) | {commit} (steps/s) | ratio, median of rounds | ratio, range |",
            "| --- | --- | --- | --- | --- |",
        ]
        threads = 0
        for case in args.cases:
            rates, threads = compare(case, sources, args.chunk, args.rounds)
            ratios = [ours / theirs for ours, theirs in zip(rates[new], rates[commit], strict=True)]
            lines.append(
                f"| {CASES[case]} | {statistics.mean(rates[new]):.0f} | {statistics.mean(rates[commit]):.0f} "
                f"| {statistics.median(ratios):.3f} | {min(ratios):.3f}-{max(ratios):.3f} |"
            )
            print(lines[-1], flush=True)
    command = " ".join(["python benchmarks/revisions.py", args.revision, *([args.new] if args.new else [])])
    command += "".join(f" --{name} {value}" for name, value in (("conf", args.conf), ("old-conf", args.old_conf)) if value)
    header = (
        f"{machine(threads)}; `{command}`: {new} against {commit}, {args.rounds} rounds of {args.chunk} steps per env, "
        f"{time.strftime('%Y-%m-%d')}"
    )
    table = "\n".join([header, "", *lines])
    print(table)
    if args.output:
        Path(args.output).write_text(table + "\n")


if __name__ == "__main__":
    main()
