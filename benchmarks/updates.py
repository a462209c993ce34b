"""
Time per gradient step of CGAC against SB3 SAC on the same networks and batch, measured side by side in one run.

    python benchmarks/updates.py                                     # the full table (a few minutes on 2 cores)
    python benchmarks/updates.py --batch-sizes 512 --critics 256,256 --paths default bf16
    python benchmarks/updates.py --batch-sizes 512 --critics 256,256 512,256 --activation elu \\
        --paths default bf16 critic-options critic-options+bf16     # the critic screen's options, float32 and bf16
    python benchmarks/updates.py --baseline 179b5ab                  # also CGAC as it was at that git revision
    python benchmarks/updates.py --paths bf16 --baseline 3ad9cec --baseline-path bf16   # one path, old against new
    python benchmarks/updates.py --e2e Pendulum-v1 HalfCheetah-v5 --baseline 179b5ab   # end to end, zoo entries

A gradient step is one critic and one actor update with their Polyak updates: CGAC's ``train()`` with
``critic_updates_per_step=1, policy_delay=1`` on a full window (its value targets are computed once per collected
step and are not part of it), and SB3 SAC's ``train(gradient_steps=1)``, which computes its targets in every step.
Every candidate (CGAC's update paths, SAC, and CGAC at ``--baseline``, imported from a git worktree of that
revision) runs in its own process with the same torch threads; the processes take turns, a short chunk of steps each,
so that all see the same machine, and the table shows median times over the chunks. GFLOP/s counts the matmul FLOPs
of a step (forward ``2 * batch * in * out`` per layer, a backward with weight gradients twice that, the backward
through the critics in CGAC's actor update, which needs no weight gradients, once that). With ``--e2e``, the
candidates are CGAC's update paths and the baseline training from the envs' ``hyperparams/cgac.yml`` entries (each
revision its own file, HalfCheetah-v5 on envpool), and the table shows env steps per second of ``learn()``.
What the hardware allows: the rows "GEMMs of CGAC's step" and "GEMMs of SAC's step" time the step's matrix products
alone, in a worker of their own that takes turns with the others, on preallocated tensors of the same shapes (each
layer's forward, its weight gradient where the update needs one, its input gradient where autograd computes one),
with nothing else (no activations, losses, optimizers or sampling); in bfloat16 too when ``bf16`` is among the paths.
Timings are printed, never asserted.
"""

import argparse
import functools
import itertools
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from statistics import median
from typing import Any

from timing import machine, take_turns  # benchmarks/timing.py

ROOT = Path(__file__).resolve().parents[1]
OBS_DIM, ACTION_DIM = 17, 6  # HalfCheetah-v5's spaces
N_ENVS, WINDOW = 128, 32  # a full window holds 4096 transitions
CRITIC_OPTIONS = {"critic_layer_norm": True, "n_bins": 101, "actor_q_reduction": "mean"}
PATHS: dict[str, dict[str, Any]] = {
    "default": {},  # the package's defaults, or with --e2e the entry as it is
    "float32": {"update_precision": "float32"},
    "bf16": {"update_precision": "bfloat16"},
    # The critic screen's options (docs/tuning.md): LayerNorm critics with 101-bin categorical heads, the actor on their mean
    "critic-options": {"policy_kwargs": CRITIC_OPTIONS},
    "critic-options+bf16": {"policy_kwargs": CRITIC_OPTIONS, "update_precision": "bfloat16"},
    # CUDA only: the updates replayed from CUDA graphs
    "cuda-graphs": {"cuda_graphs": True},
    "bf16+cuda-graphs": {"update_precision": "bfloat16", "cuda_graphs": True},
}


def matmul_gflop(
    batch: int, actor_arch: list[int], critic_arch: list[int], n_critics: int, algo: str, critic_outputs: int = 1
) -> float:
    """Matmul GFLOP of one gradient step (see the module docstring); ``critic_outputs``: bins of a categorical critic."""

    def forward(sizes: list[int]) -> float:
        return 2.0 * batch * sum(a * b for a, b in itertools.pairwise(sizes))

    actor = forward([OBS_DIM, *actor_arch, 2 * ACTION_DIM])
    critics = n_critics * forward([OBS_DIM + ACTION_DIM, *critic_arch, critic_outputs])
    # SAC: targets (actor and target critics forward), critic update, actor update with critic weight gradients.
    # CGAC: critic update, actor update through the critics without their weight gradients.
    sac = algo == "sac"
    flop = (actor + critics + 3 * critics + 3 * actor + 3 * critics) if sac else (3 * critics + 3 * actor + 2 * critics)
    return flop / 1e9


Gemm = tuple[int, int, int]  # (m, k, n): a product of an (m, k) and a (k, n) matrix


def mlp_gemms(batch: int, sizes: list[int], weight_grads: bool = False, input_grads: bool = False) -> list[Gemm]:
    """
    The matrix products of an MLP on a batch: each layer's forward, and with ``weight_grads`` / ``input_grads`` its
    weight and input gradients (the first layer's input gradient too: pass it only where the input needs one).
    """
    gemms = []
    for n_in, n_out in itertools.pairwise(sizes):
        gemms.append((batch, n_in, n_out))
        if weight_grads:
            gemms.append((n_out, batch, n_in))
        if input_grads:
            gemms.append((batch, n_out, n_in))
    return gemms


def step_gemms(batch: int, actor_arch: list[int], critic_arch: list[int], n_critics: int, algo: str) -> list[Gemm]:
    """The matrix products that autograd runs in one gradient step of CGAC or SB3 SAC (see ``matmul_gflop``)."""
    actor, critic = [OBS_DIM, *actor_arch, 2 * ACTION_DIM], [OBS_DIM + ACTION_DIM, *critic_arch, 1]

    def trained(sizes: list[int]) -> list[Gemm]:
        # Weight gradients everywhere, input gradients from the second layer on (the data need none)
        first_layer = mlp_gemms(batch, sizes[:2], weight_grads=True)
        return first_layer + mlp_gemms(batch, sizes[1:], weight_grads=True, input_grads=True)

    gemms = n_critics * trained(critic) + trained(actor)  # critic update; actor update, the actor's part
    # The actor update's pass through the critics, back to the action: SAC also computes the critics' weight gradients
    gemms += n_critics * mlp_gemms(batch, critic, weight_grads=algo == "sac", input_grads=True)
    if algo == "sac":  # SAC's targets in every step: the actor on the next observations, then the target critics
        gemms += mlp_gemms(batch, actor) + n_critics * mlp_gemms(batch, critic)
    return gemms


# --------------------------------------------------------------------------------------------------------------
# Worker: builds one model, then runs gradient steps on request ("<n>\n" on stdin, elapsed seconds on stdout)
# --------------------------------------------------------------------------------------------------------------


def worker(args: argparse.Namespace) -> None:
    if args.e2e_env is not None:
        e2e_worker(args)
        return
    if args.algo.endswith("-gemms"):
        gemm_worker(args)
        return
    import gymnasium as gym
    import numpy as np
    import torch as th
    from stable_baselines3.common.vec_env import DummyVecEnv

    th.set_num_threads(args.threads)
    th.manual_seed(0)

    class RandomEnv(gym.Env):
        """HalfCheetah-v5's spaces, random observations and rewards: the updates do not care what they learn."""

        observation_space = gym.spaces.Box(-np.inf, np.inf, (OBS_DIM,), np.float32)
        action_space = gym.spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)

        def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
            super().reset(seed=seed)
            return self.observation_space.sample(), {}

        def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
            return self.observation_space.sample(), float(self.np_random.normal()), False, False, {}

    env = DummyVecEnv([RandomEnv] * N_ENVS)
    activation = {"relu": th.nn.ReLU, "elu": th.nn.ELU}[args.activation]
    policy_kwargs = dict(net_arch=dict(pi=args.actor, qf=args.critic), activation_fn=activation)
    if args.algo == "sac":
        from stable_baselines3 import SAC

        model: Any = SAC(
            "MlpPolicy", env, batch_size=args.batch, learning_starts=0, gradient_steps=0, policy_kwargs=policy_kwargs,
            device=args.device, seed=0,
        )  # fmt: skip
        model.learn(WINDOW * N_ENVS)

        def step() -> None:
            model.train(gradient_steps=1, batch_size=args.batch)

    else:
        from sb3_cgac import CGAC

        path = dict(PATHS[args.path])
        policy_kwargs.update(path.pop("policy_kwargs", {}))
        model = CGAC(
            "MlpPolicy", env, buffer_window=WINDOW, batch_size=args.batch, critic_updates_per_step=1, policy_delay=1,
            policy_kwargs=policy_kwargs, device=args.device, seed=0, **path,
        )  # fmt: skip
        model.learn(WINDOW * N_ENVS)  # fills the window; later train() calls only run gradient steps
        step = model.train

    serve(timed_steps(step, args.device), args.warmup)


def gemm_worker(args: argparse.Namespace) -> None:
    """The matrix products of one gradient step (``step_gemms``) on preallocated tensors; a unit is one step."""
    import torch as th

    th.set_num_threads(args.threads)
    dtype = th.bfloat16 if args.path == "bf16" else th.float32
    gemms = step_gemms(args.batch, args.actor, args.critic, 2, args.algo.removesuffix("-gemms"))
    operands = [
        (th.randn(m, k, dtype=dtype, device=args.device), th.randn(k, n, dtype=dtype, device=args.device),
         th.empty(m, n, dtype=dtype, device=args.device))
        for m, k, n in gemms
    ]  # fmt: skip

    def step() -> None:
        for left, right, out in operands:
            th.mm(left, right, out=out)

    serve(timed_steps(step, args.device), args.warmup)


def timed_steps(step: Any, device: str) -> Any:
    """``run(n)`` for ``serve``: ``n`` calls of ``step``, timed to the end of their work on the device."""
    import torch as th

    def run(n_steps: int) -> tuple[float, int]:
        if device == "cuda":
            th.cuda.synchronize()
        start = time.perf_counter()
        for _ in range(n_steps):
            step()
        if device == "cuda":
            th.cuda.synchronize()
        return time.perf_counter() - start, n_steps

    return run


def serve(run: Any, warmup: int) -> None:
    """Answer "<n>" on stdin with "<seconds> <units>" on stdout: ``run(n)`` did that many units in that time."""
    run(warmup)  # warms the allocator and caches
    print("ready", flush=True)
    for line in sys.stdin:
        seconds, units = run(int(line))
        print(seconds, units, flush=True)


def e2e_worker(args: argparse.Namespace) -> None:
    """Trains the env's zoo entry; a unit is one env step (``learn()`` runs whole iterations)."""
    import tempfile

    import torch as th

    import sb3_cgac  # before torch: it sets torch's OpenMP spinning for envpool
    from sb3_cgac.zoo import build_model

    th.set_num_threads(args.threads)
    # A checkout's own hyperparams/ (the editable install maps sb3_cgac.hyperparams to the main checkout's files)
    conf_file = Path(sb3_cgac.__file__).parents[1] / "hyperparams" / "cgac.yml"
    backend = "envpool" if args.e2e_env != "Pendulum-v1" else "dummy"
    backend_kwargs = {"num_threads": args.threads} if backend == "envpool" else None
    with tempfile.TemporaryDirectory() as log_folder:
        path = dict(PATHS[args.path])
        model: Any
        model, _ = build_model(
            "cgac", args.e2e_env, backend=backend, backend_kwargs=backend_kwargs, log_folder=log_folder, device=args.device,
            hyperparams=path or None, conf_file=str(conf_file) if conf_file.exists() else None,
        )  # fmt: skip

    def run(env_steps: int) -> tuple[float, int]:
        start, before = time.perf_counter(), model.num_timesteps
        model.learn(env_steps, reset_num_timesteps=False)
        return time.perf_counter() - start, model.num_timesteps - before

    # The window fills before the first update
    serve(run, (args.warmup + model.buffer_window) * model.n_envs * model.n_steps)


# --------------------------------------------------------------------------------------------------------------
# Driver
# --------------------------------------------------------------------------------------------------------------


class Candidate:
    """A worker process and the times it reported."""

    def __init__(self, name: str, algo: str, worker_args: list[str], pythonpath: str | None = None):
        self.name, self.algo = name, algo
        self.times: list[float] = []  # seconds per unit of each turn
        environ = dict(os.environ)
        if pythonpath is not None:
            environ["PYTHONPATH"] = pythonpath + os.pathsep + environ.get("PYTHONPATH", "")
        command = [sys.executable, str(Path(__file__).resolve()), "--worker", "--algo", algo, *worker_args]
        self.process = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=environ)

    def wait_ready(self) -> None:
        # Imports may print (gymnasium-robotics does): skip to the worker's "ready"
        for line in self.process.stdout:  # type: ignore[union-attr]
            if line.strip() == "ready":
                return
        raise RuntimeError(f"{self.name}: the worker failed to start (see its error above)")

    def run(self, units: int) -> int:
        """Ask the worker for ``units`` units of work; returns how many it did."""
        self.process.stdin.write(f"{units}\n")  # type: ignore[union-attr]
        self.process.stdin.flush()  # type: ignore[union-attr]
        _, done = self.process.stdout.readline().split()  # type: ignore[union-attr]
        return int(done)

    def close(self) -> None:
        self.process.stdin.close()  # type: ignore[union-attr]
        self.process.wait()


def baseline_worktree(revision: str, directory: str) -> str:
    """A git worktree of ``revision`` of this repository, for importing the previous code."""
    command = ["git", "-C", str(ROOT), "worktree", "add", "--detach", directory, revision]
    subprocess.run(command, check=True, capture_output=True)
    return directory


def baseline_candidate(args: argparse.Namespace, common: list[str], baseline: str) -> Candidate:
    """CGAC imported from the ``--baseline`` worktree, on its ``--baseline-path`` update path."""
    name = f"CGAC at {args.baseline}" + ("" if args.baseline_path == "default" else f" {args.baseline_path}")
    return Candidate(name, "cgac", [*common, "--path", args.baseline_path], pythonpath=baseline)


def measure(args: argparse.Namespace, batch: int, critic: list[int], baseline: str | None) -> list[str]:
    common = ["--batch", str(batch), "--critic", *map(str, critic), "--actor", *map(str, args.actor),
              "--threads", str(args.threads), "--device", args.device, "--activation", args.activation,
              "--warmup", str(args.warmup)]  # fmt: skip
    candidates = [Candidate(f"CGAC {path}", "cgac", [*common, "--path", path]) for path in args.paths]
    candidates.append(Candidate("SB3 SAC", "sac", common))
    # What the hardware allows: the steps' matrix products alone
    candidates.append(Candidate("GEMMs of CGAC's step", "cgac-gemms", [*common, "--path", "float32"]))
    candidates.append(Candidate("GEMMs of SAC's step", "sac-gemms", [*common, "--path", "float32"]))
    if "bf16" in args.paths:
        candidates.append(Candidate("GEMMs of CGAC's step, bf16", "cgac-gemms", [*common, "--path", "bf16"]))
    if baseline is not None:
        candidates.append(baseline_candidate(args, common, baseline))
    run_rounds(candidates, args)
    sac_time = median(next(c for c in candidates if c.algo == "sac").times)
    default_time = median(candidates[0].times)
    rows = []
    for candidate in candidates:
        seconds = median(candidate.times)
        path = PATHS.get(candidate.name.removeprefix("CGAC "), {})
        outputs = path.get("policy_kwargs", {}).get("n_bins", 1)
        gflop = matmul_gflop(batch, args.actor, critic, 2, candidate.algo.removesuffix("-gemms"), outputs)
        vs_previous = f"{seconds / median(candidates[-1].times):.2f}" if baseline is not None else "-"
        rows.append(
            f"| {batch} | {critic} | {candidate.name} | {seconds * 1e3:.2f} | {seconds / sac_time:.2f} | "
            f"{seconds / default_time:.2f} | {vs_previous} | {gflop / seconds:.3g} |"
        )
    return rows


def measure_e2e(args: argparse.Namespace, env_id: str, baseline: str | None) -> list[str]:
    common = ["--e2e-env", env_id, "--threads", str(args.threads), "--device", args.device, "--warmup", str(args.warmup)]
    candidates = [Candidate(f"CGAC {path}", "cgac", [*common, "--path", path]) for path in args.paths]
    if baseline is not None:
        candidates.append(baseline_candidate(args, common, baseline))
    run_rounds(candidates, args)
    rows = []
    for candidate in candidates:
        seconds = median(candidate.times)
        vs_previous = f"{median(candidates[-1].times) / seconds:.2f}" if baseline is not None else "-"
        vs_default = median(candidates[0].times) / seconds
        rows.append(f"| {env_id} | {candidate.name} | {1 / seconds:,.0f} | {vs_default:.2f} | {vs_previous} |")
    return rows


def run_rounds(candidates: list[Candidate], args: argparse.Namespace) -> None:
    """Start the workers, size one request to about ``--chunk`` seconds each, then let them take turns."""
    try:
        for candidate in candidates:
            candidate.wait_ready()
        sizing = take_turns({c.name: functools.partial(c.run, 1) for c in candidates}, chunk=0.0, rounds=1)
        units = {name: max(1, round(args.chunk * done / seconds)) for name, [(done, seconds)] in sizing.items()}
        work = {c.name: functools.partial(c.run, units[c.name]) for c in candidates}
        turns = take_turns(work, chunk=0.0, rounds=args.rounds)  # one request per turn: it is sized to a chunk
        for candidate in candidates:
            candidate.times = [seconds / done for done, seconds in turns[candidate.name]]
    finally:
        for candidate in candidates:
            candidate.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[512, 4096])
    parser.add_argument("--critics", nargs="+", default=["256,256", "1024,1024,256"], help="critic hidden layers")
    parser.add_argument("--actor", type=int, nargs="+", default=[256, 256], help="actor hidden layers")
    parser.add_argument("--paths", nargs="+", default=["default", "bf16"], choices=list(PATHS))
    parser.add_argument("--baseline", help="git revision of this repository to measure too (e.g. a release tag)")
    parser.add_argument(
        "--baseline-path", default="default", choices=list(PATHS), help="update path of the --baseline candidate"
    )
    parser.add_argument("--activation", choices=["relu", "elu"], default="relu")
    parser.add_argument("--threads", type=int, default=2, help="torch threads of every candidate")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--rounds", type=int, default=7, help="chunks per candidate")
    parser.add_argument("--chunk", type=float, default=0.5, help="seconds per chunk")
    parser.add_argument("--warmup", type=int, default=20, help="untimed steps per candidate (compilation included)")
    parser.add_argument("--e2e", nargs="+", metavar="ENV", help="end-to-end steps/s of these envs' zoo entries instead")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--e2e-env", help=argparse.SUPPRESS)
    parser.add_argument("--algo", choices=["cgac", "sac", "cgac-gemms", "sac-gemms"], help=argparse.SUPPRESS)
    parser.add_argument("--path", default="default", help=argparse.SUPPRESS)
    parser.add_argument("--batch", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--critic", type=int, nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args)
        return

    print(
        f"Machine: {machine(args.threads, args.device)}, "
        + ("the entries' own networks\n" if args.e2e else f"{args.activation} networks, actor {args.actor}\n")
    )
    first = f"CGAC {args.paths[0]}"  # the ratios' reference among CGAC's paths
    if args.e2e:
        print(f"| env | candidate | steps/s | speed / {first}'s | speed / previous's |\n| --- | --- | --- | --- | --- |")
    else:
        print(f"| batch | critic | candidate | ms / step | vs SAC | vs {first} | vs previous | GFLOP/s |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    with tempfile.TemporaryDirectory() as directory:
        baseline = baseline_worktree(args.baseline, os.path.join(directory, "baseline")) if args.baseline else None
        try:
            for env_id in args.e2e or []:
                for row in measure_e2e(args, env_id, baseline):
                    print(row, flush=True)
            for critic in [] if args.e2e else args.critics:
                for batch in args.batch_sizes:
                    for row in measure(args, batch, [int(size) for size in critic.split(",")], baseline):
                        print(row, flush=True)
        finally:
            if baseline is not None:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", baseline], check=False)


if __name__ == "__main__":
    main()
