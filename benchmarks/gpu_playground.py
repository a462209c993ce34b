"""
CGAC end to end on a GPU simulator, measured side by side in one run: MuJoCo Playground (MJX) through
``PlaygroundVectorEnv`` and ``TorchVecEnv``, the whole iteration on the device. ``benchmarks/gpu.sh`` runs it on a
GPU machine; on a CPU it runs small (a check of the script, not a measurement):

    python benchmarks/gpu_playground.py --task CartpoleBalance --envs 16 --learn-envs 16 --seconds 5 \
        --learn-seconds 20 --out /tmp/gpu

A robot task such as ``--task Go1JoystickFlatTerrain`` reads its models from ``--menagerie`` (else from envpool's
asset packages), and its actors read ``state`` only, its critics every key.

It writes ``table.md`` (and ``results.json``) into ``--out`` after each measurement, so that a run cut short keeps
what it measured; a measurement that fails is listed there and the others still run. In this order:
- raw: the simulator's steps/s with random actions, through the adapter (torch tensors in and out by DLPack), at
  ``--learn-envs``;
- on CUDA, CGAC's steps/s with eager updates at ``--learn-envs`` (the gain of the graphs; a rate even if they fail);
- learning: ``--learn-seconds`` of training at ``--learn-envs`` envs of CGAC (its defaults for the device; on CUDA
  with ``cuda_graphs=True``, trained again with eager updates if the graphs fail in its first ``RETRY_WITHIN`` seconds)
  and of rsl_rl's PPO (``RslPPO``, rsl_rl's defaults: the settings of Playground's locomotion tasks), each followed by
  a deterministic evaluation of one episode on every env; their env steps/s (CGAC's is its end-to-end rate at
  ``--learn-envs``); then, over ``--split-seconds`` more with the device synchronised around
  each phase (so not part of the rate), the split of CGAC's wall-clock between the simulator's step, the rest of the
  collection (sampling, normalisation, the window), the updates and everything else: where CUDA graphs of the
  collection could pay; on CUDA, then the host syncs that torch makes in 20 more iterations of CGAC;
- CGAC with the critics and the window of the LeapCube entry (``CRITIC_OPTIONS``: LayerNorm [512, 256] critics with
  101-bin categorical heads, the actor on their mean; ``ENTRY_WINDOW``: a 256-step window, Q-GAE lambda 0.5) at
  ``--learn-envs``, at the device's batch (on a GPU the paper's 4,096): steps/s after a warm-up, beside the defaults';
- raw and CGAC (steps/s after a warm-up, and the split) at each other ``--envs``.
"""

import argparse
import gc
import json
import platform
import sys
import time
import traceback
import warnings
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.evaluation import evaluate_policy
from timing import PhaseTimer  # benchmarks/timing.py

from sb3_cgac import CGAC
from sb3_cgac.vec_env import TorchVecEnv, make_vec_env

# CGAC's learning run is trained again with eager updates if its CUDA graphs fail within these seconds (at capture);
# a later failure is not retried: the device's time limit
RETRY_WITHIN = 60.0
# The critics that the LeapCube entry of hyperparams/cgac.yml trains (docs/tuning.md, "The critic screen")
CRITIC_OPTIONS = dict(
    net_arch=dict(pi=[256, 256], qf=[512, 256]), critic_layer_norm=True, n_bins=101, actor_q_reduction="mean"
)
# ... and the window and Q-GAE lambda that the robot entries keep (the GPU defaults: 32 steps, lambda 0.95)
ENTRY_WINDOW = dict(buffer_window=256, gae_lambda=0.5)


class StopAfter(BaseCallback):
    """Stops training after ``seconds`` of wall-clock, counted from the first step."""

    def __init__(self, seconds: float):
        super().__init__()
        self.seconds = seconds
        self.start = 0.0
        self.start_steps = 0

    def _on_training_start(self) -> None:
        self.start, self.start_steps = time.perf_counter(), self.num_timesteps

    def _on_step(self) -> bool:
        return time.perf_counter() - self.start < self.seconds

    def rate(self) -> float:
        return (self.num_timesteps - self.start_steps) / (time.perf_counter() - self.start)


def synchronize() -> None:
    if th.cuda.is_available():
        th.cuda.synchronize()


def phase_split(model: CGAC, seconds: float) -> dict[str, float]:
    """Shares of CGAC's wall-clock: simulator step, the rest of the collection, updates, everything else."""
    env = model.get_env()
    assert isinstance(env, TorchVecEnv)
    timers = {name: PhaseTimer() for name in ("env", "collection", "updates")}
    originals = env.step_tensors, model.collect_rollouts, model.train
    env.step_tensors = timers["env"].wrap(env.step_tensors)  # type: ignore[method-assign]
    model.collect_rollouts = timers["collection"].wrap(model.collect_rollouts)  # type: ignore[method-assign]
    model.train = timers["updates"].wrap(model.train)  # type: ignore[method-assign]
    try:
        synchronize()
        start = time.perf_counter()
        model.learn(10**12, callback=StopAfter(seconds), reset_num_timesteps=False)
        synchronize()
        total = time.perf_counter() - start
    finally:
        del env.step_tensors, model.collect_rollouts, model.train  # the class's methods again
    assert (env.step_tensors, model.collect_rollouts, model.train) == originals
    env_s, collection_s, updates_s = (timers[name].seconds for name in ("env", "collection", "updates"))
    return {
        "env": env_s / total,
        "collection": (collection_s - env_s) / total,
        "updates": updates_s / total,
        "else": (total - collection_s - updates_s) / total,
    }


def host_syncs(model: CGAC, iterations: int) -> dict[str, Any]:
    """
    The synchronising CUDA calls that torch makes in ``iterations`` more iterations of CGAC
    (``torch.cuda.set_sync_debug_mode``), per iteration and by where they were made.
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        th.cuda.set_sync_debug_mode("warn")
        try:
            model.learn(iterations * model.n_steps * model.n_envs, reset_num_timesteps=False)
        finally:
            th.cuda.set_sync_debug_mode("default")
    places = Counter(f"{Path(w.filename).name}:{w.lineno}" for w in caught if "synchroniz" in str(w.message).lower())
    return {
        "iterations": iterations,
        "per_iteration": sum(places.values()) / iterations,
        "places": dict(places.most_common(8)),
    }


def playground(args: argparse.Namespace, n_envs: int, seed: int, random_first_episode: bool = True) -> TorchVecEnv:
    kwargs = dict(seed=seed, vec_env_kwargs=args.env_kwargs, random_first_episode=random_first_episode)
    env = make_vec_env(args.task, n_envs, backend="playground", **kwargs)  # type: ignore[arg-type]
    assert isinstance(env, TorchVecEnv)
    return env


def raw_rate(args: argparse.Namespace, n_envs: int) -> float:
    env = playground(args, n_envs, seed=0, random_first_episode=False)
    venv, device = env.venv, env.device
    venv.reset(seed=0)
    action_dim = int(np.prod(env.action_space.shape))  # type: ignore[arg-type]
    for _ in range(2):  # compiles the step
        venv.step(th.zeros(n_envs, action_dim, device=device))
    synchronize()
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < args.seconds:
        venv.step(th.rand(n_envs, action_dim, device=device) * 2 - 1)
        steps += 1
    synchronize()
    return steps * n_envs / (time.perf_counter() - start)


def build(
    algo: str, n_envs: int, args: argparse.Namespace, cuda_graphs: bool = False, critic_options: bool = False
) -> BaseAlgorithm:
    env = playground(args, n_envs, seed=0)
    dict_obs = isinstance(env.observation_space, spaces.Dict)
    policy = "MultiInputPolicy" if dict_obs else "MlpPolicy"
    # Playground's robot tasks: the actors read what the robot senses ("state"), the critics everything
    actor_keys = ["state"] if dict_obs and "state" in env.observation_space.spaces else None  # type: ignore[attr-defined]
    if algo == "cgac":
        kwargs: dict[str, Any] = dict(actor_keys=actor_keys, **(CRITIC_OPTIONS if critic_options else {}))
        window: dict[str, Any] = ENTRY_WINDOW if critic_options else {}
        return CGAC(policy, env, seed=0, device=args.device, cuda_graphs=cuda_graphs, policy_kwargs=kwargs, **window)
    from sb3_cgac.rsl_rl import RslPPO

    return RslPPO(policy, env, seed=0, device=args.device, actor_keys=actor_keys)


def train_rate(model: BaseAlgorithm, seconds: float, warmup_steps: int) -> float:
    model.learn(warmup_steps)  # compiles the simulator, fills the window, warms the kernels
    stopper = StopAfter(seconds)
    model.learn(10**12, callback=stopper, reset_num_timesteps=False)
    return stopper.rate()


def learn_and_evaluate(algo: str, args: argparse.Namespace, cuda_graphs: bool) -> tuple[BaseAlgorithm, float, float]:
    """``--learn-seconds`` of training at ``--learn-envs`` envs; the model, its env steps/s and its evaluation return."""
    model = build(algo, args.learn_envs, args, cuda_graphs=cuda_graphs)
    rate = train_rate(model, args.learn_seconds, warmup_steps=args.learn_envs * 40)
    return model, rate, evaluate(model, args, args.learn_envs)


def evaluate(model: BaseAlgorithm, args: argparse.Namespace, n_envs: int) -> float:
    eval_env = playground(args, n_envs, seed=10_000, random_first_episode=False)
    returns, _ = evaluate_policy(model, eval_env, n_eval_episodes=n_envs, deterministic=True)
    return float(returns)  # type: ignore[arg-type]


def machine(device: str) -> str:
    gpu = th.cuda.get_device_name() if th.cuda.is_available() else "no GPU"
    driver = ""
    if th.cuda.is_available():
        import subprocess

        query = ["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"]
        driver = subprocess.run(query, capture_output=True, text=True, check=False).stdout.strip()
    import jax
    import mujoco

    return (
        f"{gpu} (driver {driver or '-'}), {platform.processor() or platform.machine()}; torch {th.__version__}, "
        f"JAX {jax.__version__} ({jax.default_backend()}), MuJoCo {mujoco.__version__}, device {device}"
    )


def phases(args: argparse.Namespace) -> list[tuple[str, Callable[[dict[str, Any]], None]]]:
    """
    The measurements in the order they run: what the issue's targets need first (raw and CGAC at ``--learn-envs``, both
    learning runs), then the other env counts, so that a run cut short by its time limit still has those.
    """

    trained: dict[str, CGAC] = {}  # the learning run's model, for the count of host syncs after it

    def raw(n_envs: int) -> Callable[[dict[str, Any]], None]:
        def measure(results: dict[str, Any]) -> None:
            results["raw"][n_envs] = raw_rate(args, n_envs)
            print(f"raw {n_envs}: {results['raw'][n_envs]:,.0f} steps/s", flush=True)

        return measure

    def learning(algo: str) -> Callable[[dict[str, Any]], None]:
        def measure(results: dict[str, Any]) -> None:
            cuda_graphs = args.cuda_graphs and algo == "cgac"
            start = time.perf_counter()
            try:
                model, rate, final = learn_and_evaluate(algo, args, cuda_graphs)
            except Exception as error:
                # CUDA graphs that fail in the first seconds (their capture): CGAC trains again with eager updates, so
                # that the comparison of returns still has it; a later failure is not retried (the time limit)
                if not cuda_graphs or time.perf_counter() - start > RETRY_WITHIN:
                    raise
                traceback.print_exc()
                results["errors"].append(
                    f"learning cgac with CUDA graphs: {type(error).__name__}: {str(error)[:300]} (trained again with eager "
                    "updates, the learning row's)"
                )
                cuda_graphs = False
                gc.collect()
                model, rate, final = learn_and_evaluate(algo, args, cuda_graphs)
            results["learning"][algo] = {"steps_per_s": rate, "steps": model.num_timesteps, "return": final}
            print(f"{algo}: {rate:,.0f} steps/s, {model.num_timesteps:,} steps, return {final:.1f}", flush=True)
            if isinstance(model, CGAC):  # after the evaluation: the learning run's steps and return are the budget's
                results["cgac" if cuda_graphs == args.cuda_graphs else "cgac_eager"][args.learn_envs] = rate
                results["split"][args.learn_envs] = phase_split(model, args.split_seconds)
                trained["cgac"] = model

        return measure

    def syncs(results: dict[str, Any]) -> None:
        # The collection and the updates should not wait for the device: one read of the statistics per iteration
        model = trained.pop("cgac", None)
        if model is not None and th.cuda.is_available():
            results["syncs"] = host_syncs(model, iterations=20)
            print(f"host syncs: {results['syncs']}", flush=True)

    def throughput(n_envs: int, cuda_graphs: bool, critic_options: bool = False) -> Callable[[dict[str, Any]], None]:
        def measure(results: dict[str, Any]) -> None:
            model = build("cgac", n_envs, args, cuda_graphs=cuda_graphs, critic_options=critic_options)
            assert isinstance(model, CGAC)
            rate = train_rate(model, args.seconds, warmup_steps=40 * n_envs)
            if critic_options:
                results["cgac_critic"][n_envs] = rate
                print(
                    f"cgac {n_envs}, LeapCube's critics and window, batch {model.batch_size}: {rate:,.0f} steps/s", flush=True
                )
                return
            if cuda_graphs != args.cuda_graphs:  # the other update path, for the gain of the graphs
                results["cgac_eager"][n_envs] = rate
                print(f"cgac {n_envs}, eager updates: {rate:,.0f} steps/s", flush=True)
                return
            results["cgac"][n_envs] = rate
            results["split"][n_envs] = phase_split(model, args.split_seconds)
            print(f"cgac {n_envs}: {rate:,.0f} steps/s, split {results['split'][n_envs]}", flush=True)

        return measure

    found: list[tuple[str, Callable[[dict[str, Any]], None]]] = [(f"raw {args.learn_envs}", raw(args.learn_envs))]
    if args.cuda_graphs:  # first: a rate at --learn-envs even if the graphs fail on this path
        found.append((f"cgac {args.learn_envs} eager", throughput(args.learn_envs, cuda_graphs=False)))
    found += [("learning cgac", learning("cgac")), ("host syncs", syncs), ("learning rsl_ppo", learning("rsl_ppo"))]
    critic_options = throughput(args.learn_envs, args.cuda_graphs, critic_options=True)
    found.append((f"cgac {args.learn_envs} critic options", critic_options))
    for n_envs in args.envs:
        if n_envs != args.learn_envs:
            found += [(f"raw {n_envs}", raw(n_envs)), (f"cgac {n_envs}", throughput(n_envs, args.cuda_graphs))]
    return found


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="CheetahRun", help="a MuJoCo Playground task, e.g. Go1JoystickFlatTerrain")
    parser.add_argument("--menagerie", default=None, help="folder of mujoco_menagerie's robots (see use_menagerie)")
    parser.add_argument("--envs", type=int, nargs="+", default=[1024, 4096, 16384])
    parser.add_argument("--learn-envs", type=int, default=4096)
    # 8 s: millions of steps at GPU rates; the two learning runs take 6 of the 8 minutes, the rest holds three
    # compilations of the task and seven throughput measurements
    parser.add_argument("--seconds", type=float, default=8.0, help="timed seconds of each throughput measurement")
    parser.add_argument("--learn-seconds", type=float, default=180.0)
    parser.add_argument("--split-seconds", type=float, default=5.0, help="seconds of CGAC's wall-clock split per --envs")
    parser.add_argument("--impl", default="jax", help="MuJoCo's JAX implementation: jax (MJX) or warp")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    args.device = "cuda" if th.cuda.is_available() else "cpu"
    args.cuda_graphs = args.device == "cuda"  # CGAC's fast update path on a GPU; the eager one is measured beside it
    args.env_kwargs = {"impl": args.impl, "menagerie_path": args.menagerie}
    args.out.mkdir(parents=True, exist_ok=True)
    results: dict[str, Any] = {"machine": machine(args.device), "task": args.task, "errors": []}
    results.update({key: {} for key in ("raw", "cgac", "cgac_eager", "cgac_critic", "split", "learning")})
    # One phase that fails (out of memory at 16,384 envs, say) is reported in the table; the others still run
    for name, measure in phases(args):
        try:
            measure(results)
        except Exception as error:  # keep what the other phases measure
            traceback.print_exc()
            results["errors"].append(f"{name}: {type(error).__name__}: {str(error)[:300]}")
        gc.collect()  # the phase's envs and model (JAX's and torch's device memory) before the next one
        if th.cuda.is_available():
            th.cuda.empty_cache()
        (args.out / "results.json").write_text(json.dumps(results, indent=1))
        (args.out / "table.md").write_text(table(results, args))
    print(table(results, args))
    return 1 if results["errors"] else 0


def table(results: dict[str, Any], args: argparse.Namespace) -> str:
    updates = "CUDA graphs of the updates" if args.cuda_graphs else "eager updates"
    lines = [f"Machine: {results['machine']}", f"Task: {results['task']} (MuJoCo Playground, impl={args.impl})", ""]
    lines += [
        f"| envs | raw simulator steps/s | CGAC end-to-end steps/s ({updates}) | CGAC / raw | CGAC, eager updates | "
        "CGAC's time: simulator / collection / updates / else |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for n_envs in sorted(set(args.envs) | {args.learn_envs}):
        raw, cgac, split = results["raw"].get(n_envs), results["cgac"].get(n_envs), results["split"].get(n_envs)
        eager = results["cgac_eager"].get(n_envs)
        ratio = f"{cgac / raw:.2f}" if raw and cgac else "-"
        shares = " / ".join(f"{split[phase]:.0%}" for phase in ("env", "collection", "updates", "else")) if split else "-"
        eager_text = f"{eager:,.0f}" if eager else "-"
        lines.append(f"| {n_envs:,} | {raw or 0:,.0f} | {cgac or 0:,.0f} | {ratio} | {eager_text} | {shares} |")
    critic_rate, default_rate = results.get("cgac_critic", {}).get(args.learn_envs), results["cgac"].get(args.learn_envs)
    if critic_rate:
        ratio = f" ({critic_rate / default_rate:.2f}x the defaults')" if default_rate else ""
        lines += [
            "",
            f"CGAC with the LeapCube entry's critics (LayerNorm [512, 256], 101-bin categorical heads, the actor on their "
            f"mean) and window (256 steps, lambda 0.5) at {args.learn_envs:,} envs, {updates}: {critic_rate:,.0f} "
            f"steps/s{ratio}.",
        ]
    lines += [
        "",
        f"Learning: {args.learn_seconds:.0f} s of training at {args.learn_envs:,} envs (after a warm-up of 40 steps per "
        f"env; CGAC with {updates}), then one deterministic episode on each of {args.learn_envs:,} envs.",
        "",
    ]
    lines += ["| algorithm | env steps/s | env steps | evaluation return |", "| --- | --- | --- | --- |"]
    for algo, found in results["learning"].items():
        lines.append(f"| {algo} | {found['steps_per_s']:,.0f} | {found['steps']:,} | {found['return']:.1f} |")
    if results.get("syncs"):
        syncs = results["syncs"]
        places = ", ".join(f"{place} ({count})" for place, count in syncs["places"].items()) or "none"
        lines += [
            "",
            f"Host syncs per CGAC iteration (torch.cuda.set_sync_debug_mode, {syncs['iterations']} iterations at "
            f"{args.learn_envs:,} envs after the learning run): {syncs['per_iteration']:.1f}; made at: {places}",
        ]
    if results["errors"]:
        lines += ["", "Failed (the traceback is in the log):", *(f"- {error}" for error in results["errors"])]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    sys.exit(main())
