"""
Throughput of CGAC on large vectorised MuJoCo envs, measured side by side in one run.

    python benchmarks/throughput.py --output throughput.md   # full table (about 15 minutes on 2 cores; docs/performance.md)
    python benchmarks/throughput.py --envs HalfCheetah-v5 --n-envs 256 --backends envpool --no-baselines
    python benchmarks/throughput.py --zoo-split Pendulum-v1 --e2e-seconds 20   # split of CGAC built from its YAML entry only

For each env, number of envs and backend it prints:
- raw: vec-env steps/s with random actions (the simulator's ceiling here);
- collect: CGAC collection-only steps/s (averaged-actor actions, buffer writes) and its ratio to raw, both
  measured on the same env in alternating short chunks (this machine's speed drifts by +-20% within seconds);
- e2e: CGAC end-to-end steps/s with the default update settings, and the split of wall-clock between env
  stepping, inference (averaged-actor sampling), updates (targets + gradient steps) and everything else;
- buffer: rollout-buffer bytes over raw transition bytes.
It also measures SB3 PPO and SAC end to end with their zoo settings (hyperparams/ppo.yml, sac.yml) in the
same run. Timings are ratios measured here, never asserted anywhere.
"""

import argparse
import tempfile
import time
import warnings
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper
from timing import PhaseTimer, machine, rate, take_turns  # benchmarks/timing.py

from sb3_cgac import CGAC
from sb3_cgac.vec_env import make_vec_env, register_optional_envs

LEGEND = """\
raw: vec-env steps/s with random actions. collect: CGAC collection only (averaged-actor actions and buffer writes),
measured on the same env in alternation with raw, in short chunks (see the command); ratio = collect / raw. e2e:
CGAC end to end with the paper's update schedule (1 new step per iteration, 32-step window, batch
min(4096, 32 x n_envs), 2 critic + 1 actor updates per step, [256, 256] networks: the defaults from 1024 envs on;
below 1024 envs the defaults run 4 critic updates per step), and the split of its wall-clock
between env stepping, inference (sampling the averaged actor), updates (value targets and gradient steps) and
everything else. buffer / raw bytes: rollout buffer memory over the bytes of the transitions themselves
(observation, action, next action, reward, two flags). SubprocVecEnv runs a process per env and is skipped beyond
64. The machine's speed drifts by +-20% between runs."""

BACKEND_NAMES = {
    "dummy": "DummyVecEnv",
    "subproc": "SubprocVecEnv",
    "envpool": "envpool",
    "gymnasium": "gymnasium sync",
    "gymnasium_async": "gymnasium async",
}
# SubprocVecEnv runs one process per env: beyond this, the processes alone exhaust 2 cores and 24 GiB
MAX_PROCESSES = 64


class TimedVecEnv(VecEnvWrapper):
    """Accumulates the wall-clock spent inside the wrapped env's step."""

    def __init__(self, venv: VecEnv):
        super().__init__(venv)
        self.seconds = 0.0

    def reset(self):
        return self.venv.reset()

    def step_async(self, actions: np.ndarray) -> None:
        start = time.perf_counter()
        self.venv.step_async(actions)
        self.seconds += time.perf_counter() - start

    def step_wait(self):
        start = time.perf_counter()
        result = self.venv.step_wait()
        self.seconds += time.perf_counter() - start
        return result


class StopAfter(BaseCallback):
    def __init__(self, seconds: float):
        super().__init__()
        self.seconds = seconds

    def _on_training_start(self) -> None:
        self.start = time.perf_counter()

    def _on_step(self) -> bool:
        return time.perf_counter() - self.start < self.seconds


def raw_and_collection(env: VecEnv, seconds: float, chunk: float) -> tuple[float, float, int, int]:
    """Raw vec-env steps/s (random actions) and CGAC collection-only steps/s, measured alternately on the same env."""
    model = CGAC("MlpPolicy", env, seed=0)
    _, callback = model._setup_learn(10**12)
    callback.on_training_start(locals(), globals())
    action_shape = env.action_space.shape or ()
    actions = np.random.default_rng(0).uniform(-1, 1, (16, env.num_envs, *action_shape)).astype(np.float32)
    counter = iter(range(10**12))

    def raw_step() -> int:
        env.step(actions[next(counter) % 16])
        return env.num_envs

    def collect_step() -> int:
        model.collect_rollouts(env, callback, model.rollout_buffer, n_rollout_steps=1)
        return env.num_envs

    steps = {"raw": raw_step, "collect": collect_step}
    take_turns(steps, chunk, seconds=0.5)  # warm-up
    turns = take_turns(steps, chunk, seconds=seconds)
    buffer = model.rollout_buffer
    return rate(turns["raw"]), rate(turns["collect"]), buffer.nbytes(), buffer.raw_transition_nbytes()


def end_to_end(env: VecEnv, seconds: float, device: str, **cgac_kwargs: Any) -> dict[str, float]:
    """CGAC end to end (the paper's schedule unless ``cgac_kwargs`` say otherwise) and the split of its wall-clock."""
    kwargs = {"critic_updates_per_step": 2, **cgac_kwargs}
    return timed_split(CGAC("MlpPolicy", TimedVecEnv(env), device=device, seed=0, **kwargs), seconds)


def zoo_split(env_id: str, seconds: float, backend: str) -> dict[str, float]:
    """CGAC built from its YAML entry (hyperparams/cgac.yml) as the zoo builds it, and the split of its wall-clock."""
    from sb3_cgac.zoo import build_model

    with tempfile.TemporaryDirectory() as log_folder:
        model, _ = build_model("cgac", env_id, seed=0, backend=backend, log_folder=log_folder, device="cpu")
    env = model.get_env()
    assert env is not None
    model.set_env(TimedVecEnv(env))
    return timed_split(model, seconds)  # type: ignore[arg-type]


def timed_split(model: CGAC, seconds: float) -> dict[str, float]:
    """Steps/s of ``model`` (whose env is a ``TimedVecEnv``) over ``seconds`` of training, and its wall-clock split."""
    timed_env = model.get_env()
    assert isinstance(timed_env, TimedVecEnv)
    # Fill the window first: updates start once it holds a minibatch
    model.learn(model.buffer_window * timed_env.num_envs, log_interval=10**9)
    timer_inference, timer_update = PhaseTimer(), PhaseTimer()
    model.actor_avg.sample = timer_inference.wrap(model.actor_avg.sample)  # type: ignore[method-assign]
    model.train = timer_update.wrap(model.train)  # type: ignore[method-assign]
    timed_env.seconds = 0.0
    start_steps, start = model.num_timesteps, time.perf_counter()
    model.learn(10**12, callback=StopAfter(seconds), reset_num_timesteps=False, log_interval=10**9)
    total = time.perf_counter() - start
    env_s, inference_s, update_s = timed_env.seconds, timer_inference.seconds, timer_update.seconds
    return {
        "sps": (model.num_timesteps - start_steps) / total,
        "env": env_s / total,
        "inference": inference_s / total,
        "update": update_s / total,
        "else": (total - env_s - inference_s - update_s) / total,
    }


def baseline_throughput(algo: str, env_id: str, seconds: float) -> tuple[float, str]:
    """SB3 PPO / SAC end to end with their zoo entry (hyperparams/<algo>.yml), built as rl_zoo3 builds them."""
    from sb3_cgac.zoo import build_model

    with tempfile.TemporaryDirectory() as log_folder:
        model, manager = build_model(algo, env_id, seed=0, log_folder=log_folder, device="cpu")
    warmup = model.n_steps * model.n_envs if algo == "ppo" else model.learning_starts + 200  # type: ignore[attr-defined]
    model.learn(warmup)
    start_steps, start = model.num_timesteps, time.perf_counter()
    model.learn(10**12, callback=StopAfter(seconds), reset_num_timesteps=False)
    sps = (model.num_timesteps - start_steps) / (time.perf_counter() - start)
    return sps, f"zoo settings, {manager.n_envs} env{'s' if manager.n_envs > 1 else ''}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=["HalfCheetah-v5", "Ant-v5"])
    parser.add_argument("--n-envs", nargs="+", type=int, default=[16, 64, 256, 1024])
    parser.add_argument(
        "--backends", nargs="+", default=["dummy", "subproc", "envpool", "gymnasium"], choices=list(BACKEND_NAMES)
    )
    parser.add_argument("--seconds", type=float, default=6.0, help="measuring time of raw and of collection, each")
    parser.add_argument("--chunk", type=float, default=0.1, help="raw and collection alternate in chunks of this length")
    parser.add_argument("--e2e-seconds", type=float, default=4.0, help="training time of each end-to-end measurement")
    parser.add_argument("--no-baselines", action="store_true", help="skip SB3 PPO and SAC")
    parser.add_argument("--output", default=None, help="also write the tables to this markdown file")
    parser.add_argument(
        "--zoo-split",
        nargs="+",
        default=None,
        metavar="ENV_ID",
        help="only the e2e split of CGAC built from "
        "its hyperparams/cgac.yml entry for these envs (--e2e-seconds of training each, --backends' first)",
    )
    args = parser.parse_args()
    warnings.filterwarnings("ignore", category=UserWarning)
    register_optional_envs()  # Adroit, MyoSuite
    if args.zoo_split:
        backend = args.backends[0] if args.backends != parser.get_default("backends") else "dummy"
        print(
            f"CGAC from hyperparams/cgac.yml, {backend} backend, {args.e2e_seconds:g} s of training, {th.get_num_threads()} "
            "torch threads: steps/s and the split of wall-clock between env / inference / update / else"
        )
        for env_id in args.zoo_split:
            split = zoo_split(env_id, args.e2e_seconds, backend)
            print(
                f"{env_id}: {split['sps']:,.0f} steps/s, {split['env']:.0%} / {split['inference']:.0%} / "
                f"{split['update']:.0%} / {split['else']:.0%}",
                flush=True,
            )
        return
    devices = ["cpu"] + (["cuda"] if th.cuda.is_available() else [])

    lines = [
        "# CGAC throughput",
        "",
        LEGEND,
        "",
        f"Machine: {machine(th.get_num_threads(), ', '.join(devices))}.",
        f"Command: python benchmarks/throughput.py --seconds {args.seconds:g} --chunk {args.chunk:g} "
        f"--e2e-seconds {args.e2e_seconds:g}"
        + (f" --envs {' '.join(args.envs)}" if args.envs != parser.get_default("envs") else "")
        + (f" --n-envs {' '.join(map(str, args.n_envs))}" if args.n_envs != parser.get_default("n_envs") else "")
        + (f" --backends {' '.join(args.backends)}" if args.backends != parser.get_default("backends") else "")
        + (" --no-baselines" if args.no_baselines else "")
        + (f" --output {args.output}" if args.output else ""),
        "",
        "| env | n_envs | backend | raw steps/s | collect steps/s (ratio) | e2e steps/s | env / infer / update / else "
        "| buffer / raw bytes |" + "".join(f" e2e {d} steps/s |" for d in devices[1:]),
        "| --- | --- | --- | --- | --- | --- | --- | --- |" + " --- |" * (len(devices) - 1),
    ]
    print("\n".join(lines), flush=True)
    for env_id in args.envs:
        for n_envs in args.n_envs:
            for backend in args.backends:
                name = BACKEND_NAMES[backend]
                if backend in ("subproc", "gymnasium_async") and n_envs > MAX_PROCESSES:
                    # As many cells as the header, so that the table stays rectangular
                    skipped = f"skipped: one process per env, > {MAX_PROCESSES} processes"
                    row = f"| {env_id} | {n_envs} | {name} | {skipped} | | | | |"
                    lines.append(row)
                    print(row, flush=True)
                    continue

                def env(backend: str = backend, n_envs: int = n_envs, env_id: str = env_id) -> VecEnv:
                    return make_vec_env(env_id, n_envs=n_envs, backend=backend, seed=0)

                measured_env = env()
                raw, collect, buffer_bytes, raw_bytes = raw_and_collection(measured_env, args.seconds, args.chunk)
                measured_env.close()
                e2e_env = env()
                e2e = end_to_end(e2e_env, args.e2e_seconds, "cpu")
                e2e_env.close()
                extra = ""
                for device in devices[1:]:
                    device_env = env()
                    extra += f" {end_to_end(device_env, args.e2e_seconds, device)['sps']:,.0f} |"
                    device_env.close()
                row = (
                    f"| {env_id} | {n_envs} | {name} | {raw:,.0f} | {collect:,.0f} ({collect / raw:.0%}) | {e2e['sps']:,.0f} "
                    f"| {e2e['env']:.0%} / {e2e['inference']:.0%} / {e2e['update']:.0%} / {e2e['else']:.0%} "
                    f"| {buffer_bytes / raw_bytes:.2f} |{extra}"
                )
                lines.append(row)
                print(row, flush=True)
        if not args.no_baselines:
            for algo in ("ppo", "sac"):
                sps, description = baseline_throughput(algo, env_id, args.e2e_seconds)
                row = f"| {env_id} | SB3 {algo.upper()} ({description}) | | | | {sps:,.0f} | | |"
                lines.append(row)
                print(row, flush=True)
    if args.output:
        with open(args.output, "w") as file:
            file.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
