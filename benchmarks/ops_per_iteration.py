"""
The torch operations that CGAC dispatches per iteration on the torch-native path (``TorchVecEnv``), by phase, counted
with torch's profiler on the CPU. On a GPU each one is at least one kernel launched from Python, a few microseconds of
host time: the updates' share is what CUDA graphs replace by one launch per update (``cuda_graphs=True``); the rest
(the Q-GAE targets, the minibatch sampling, the collection) stays. ``benchmarks/gpu.sh`` measures the time itself.

    python benchmarks/ops_per_iteration.py --env Pendulum-v1 --n-envs 64 --iterations 20

The simulator's own step is not counted (a GPU simulator dispatches its own work, here a NumPy env steps).
"""

import argparse
import collections
from collections.abc import Callable
from typing import Any

from torch.profiler import ProfilerActivity, profile, record_function

from sb3_cgac import CGAC
from sb3_cgac.vec_env import TorchVecEnv, make_vec_env

PHASES = {
    "collection": "the collection (sampling, sanitising, normalisation, the window)",
    "targets": "the Q-GAE targets (the target critic on the new steps, the recursion over the window)",
    "sampling": "the minibatches",
    "updates": "the updates (eager here; on CUDA with cuda_graphs=True one graph replay per update) and statistics",
}


def in_phase(name: str, function: Callable[..., Any]) -> Callable[..., Any]:
    def call(*args: Any, **kwargs: Any) -> Any:
        with record_function(f"phase:{name}"):
            return function(*args, **kwargs)

    return call


def count_ops(model: CGAC, iterations: int) -> dict[str, tuple[float, float]]:
    """
    Top-level torch operations per iteration of ``model.learn``, by the innermost phase they ran in: all of them, and
    those that ``Tensor.numpy()`` makes (a CPU tensor's conversions: no kernel, and not made on a GPU).
    """
    env = model.get_env()
    assert isinstance(env, TorchVecEnv)
    buffer = model.rollout_buffer
    # Instance attributes over the methods, removed afterwards
    model.collect_rollouts = in_phase("collection", model.collect_rollouts)  # type: ignore[method-assign]
    model.train = in_phase("updates", model.train)  # type: ignore[method-assign]
    buffer.compute_returns = in_phase("targets", buffer.compute_returns)  # type: ignore[method-assign]
    buffer.sample = in_phase("sampling", buffer.sample)  # type: ignore[method-assign]
    env.venv.step = in_phase("simulator", env.venv.step)  # type: ignore[method-assign]
    try:
        with profile(activities=[ProfilerActivity.CPU], with_stack=True) as profiler:  # the stack: Python's calls
            model.learn(iterations * model.n_steps * model.n_envs, reset_num_timesteps=False)
    finally:
        del model.collect_rollouts, model.train, buffer.compute_returns, buffer.sample, env.venv.step
    counts: collections.Counter[str] = collections.Counter()
    conversions: collections.Counter[str] = collections.Counter()
    for event in profiler.events():
        if not event.name.startswith("aten::"):
            continue
        parent, phase, in_numpy = event.cpu_parent, None, False
        while parent is not None and not parent.name.startswith("aten::"):  # an op inside another op is not counted
            if phase is None and parent.name.startswith("phase:"):
                phase = parent.name[len("phase:") :]
            in_numpy = in_numpy or parent.name.startswith("<built-in method numpy of Tensor")
            parent = parent.cpu_parent
        if parent is None and phase in PHASES:
            counts[phase] += 1
            conversions[phase] += in_numpy
    return {phase: (counts[phase] / iterations, conversions[phase] / iterations) for phase in PHASES}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Pendulum-v1")
    parser.add_argument("--n-envs", type=int, default=64)
    parser.add_argument("--iterations", type=int, default=20)
    args = parser.parse_args()
    env = make_vec_env(args.env, args.n_envs, backend="gymnasium_torch", seed=0)
    model = CGAC("MlpPolicy", env, seed=0, policy_kwargs=dict(normalize_observations=True))
    model.learn(2 * model.buffer_window * model.n_envs)  # a full window: the targets' recursion at its length
    ops = count_ops(model, args.iterations)
    print(f"{args.env}, {args.n_envs} envs, CGAC's CPU defaults (batch {model.batch_size}, ", end="")
    print(f"{model.critic_updates_per_step} critic updates per step), {args.iterations} iterations\n")
    print("| phase | torch operations per iteration | of them `.numpy()` conversions (CPU only) |\n| --- | --- | --- |")
    for phase, description in PHASES.items():
        print(f"| {description} | {ops[phase][0]:,.0f} | {ops[phase][1]:,.0f} |")
    outside = sum(ops[phase][0] for phase in PHASES if phase != "updates")
    print(f"\nOutside the updates: {outside:,.0f} per iteration.")


if __name__ == "__main__":
    main()
