"""
Where CGAC's collection step loses time against the raw env step (the companion of throughput.py).

    python benchmarks/collection_profile.py                                  # envpool HalfCheetah-v5, 256 envs
    python benchmarks/collection_profile.py --env Ant-v5 --n-envs 1024 --backend envpool

It prints, measured in one run:
1. the averaged actor's forward pass (two draws, as in collection) on its own, right after an env step and
   after 5 ms with the cores idle (no env step), with torch's default threads and with one thread, and with its
   hidden layers in bfloat16 (medians over many calls), and the same for 20 small torch ops, whose time is all
   dispatch overhead (it shows what running from cold caches costs per torch call; the idle case shows what waking
   idle cores costs, large on some VMs);
2. steps/s of the raw env (random actions), of a bare loop (env step, float32 conversion, the forward pass and
   numpy writes, nothing else) and of CGAC's real collection step, alternating in short chunks on the same env,
   as ratios to raw, and the mean time of the env step inside each (the simulator itself runs slower right after
   inference). The bare loop bounds what trimming the bookkeeping around the forward pass can give; the last
   loop is CGAC's collection with the averaged actor's hidden layers run in bfloat16 (a copy made once; cheaper
   matrix multiplies on CPUs with AVX512-BF16 or AMX, see part 1), which shows what a cheaper forward pass gives;
3. (envpool backend) envpool's own API, alternating in chunks: raw with uniform actions, raw with a bank of the
   averaged actor's actions (the simulator's cost depends on the actions), the synchronous loop (step, forward),
   one that keeps the envs in step (all actions sent at once, envpool's batch_size = n_envs / 2, one torch thread:
   the forward pass of the half that finishes first overlaps the simulation of the rest), and an asynchronous one
   (same batch_size) whose forward pass of one half overlaps the simulation of the other. The asynchronous loop
   shows what overlapping inference with simulation could give; CGAC cannot use it as is, because envpool's recv
   hands back whichever envs finish first, so the envs drift apart by a step or two (printed), while the on-policy
   window stores every env at the same step. Last, the raw and synchronous loops again on a pool whose worker
   threads are pinned to one core each (envpool's ``thread_affinity_offset``; sb3_cgac does not pin by default).
"""

import argparse
import copy
import os
import time
from collections.abc import Callable
from typing import Any

from sb3_cgac import CGAC
from sb3_cgac.vec_env import make_vec_env

import numpy as np
import torch as th
from throughput import TimedVecEnv, alternate


class BFloat16Sampler(th.nn.Module):
    """The averaged actor's ``sample`` with its hidden layers in bfloat16 (mean layer, noise and squashing in float32)."""

    def __init__(self, actor: Any):
        super().__init__()
        self.latent_pi = copy.deepcopy(actor.latent_pi).to(th.bfloat16)
        self.mu, self.log_std = actor.mu, actor.log_std

    def sample(self, obs: th.Tensor, n_samples: int) -> th.Tensor:
        mean_actions = self.mu(self.latent_pi(obs.to(th.bfloat16)).float())
        noise = th.randn((n_samples, *mean_actions.shape), dtype=mean_actions.dtype)
        return th.tanh(mean_actions + self.log_std.exp() * noise)


def forward_timings(model: CGAC, env: Any, actions: np.ndarray, calls: int) -> dict[str, float]:
    """Median seconds of one forward pass (and of 20 small ops): alone, right after an env step, after 5 ms idle."""
    obs = th.as_tensor(env.reset(), dtype=th.float32)
    threads = th.get_num_threads()
    bf16 = BFloat16Sampler(model.actor_avg)
    variants: list[tuple[Callable[[th.Tensor, int], th.Tensor], int, str, bool]] = [
        (model.actor_avg.sample, threads, "", True),
        (model.actor_avg.sample, 1, "", True),
        (bf16.sample, threads, "bfloat16 hidden layers, ", False),
    ]
    timings: dict[str, list[float]] = {}
    for sample, n_threads, prefix, with_idle in variants:
        for before in ("alone", "after an env step", "after 5 ms idle")[: 3 if with_idle else 2]:
            th.set_num_threads(n_threads)
            name = f"{prefix}{before}, {n_threads} torch thread{'s' * (n_threads > 1)}"
            timings[name] = []
            for call in range(calls):
                if before == "after an env step":
                    obs = th.as_tensor(env.step(actions[call % len(actions)])[0], dtype=th.float32)
                elif before == "after 5 ms idle":
                    time.sleep(0.005)  # as long as a step of 256 HalfCheetah envs, but with the cores idle
                start = time.perf_counter()
                with th.inference_mode():
                    sample(obs, 2)
                timings[name].append(time.perf_counter() - start)
    th.set_num_threads(threads)
    small = th.zeros(8)
    for after_step in (False, True):
        name = f"20 small torch ops, {'after an env step' if after_step else 'alone'}"
        timings[name] = []
        for call in range(calls):
            if after_step:
                env.step(actions[call % len(actions)])
            start = time.perf_counter()
            value = small
            for _ in range(20):
                value = value + 1.0
            timings[name].append(time.perf_counter() - start)
    return {name: float(np.median(values[calls // 10 :])) for name, values in timings.items()}


class StepFunctions:
    """Part 2's loops on one env, each with the time it spends inside the env's step (the simulator's share)."""

    def __init__(self, model: CGAC, env: Any, actions: np.ndarray):
        self.model, self.env, self.actions = model, TimedVecEnv(env), actions
        self.calls = 0
        window = 32
        self.obs_store = np.zeros((window, env.num_envs, *env.observation_space.shape), dtype=np.float32)
        self.reward_store = np.zeros((window, env.num_envs), dtype=np.float32)
        self.done_store = np.zeros((window, env.num_envs), dtype=bool)
        self.action_store = np.zeros((window, env.num_envs, *env.action_space.shape), dtype=np.float32)
        self.pending = np.zeros((env.num_envs, *env.action_space.shape), dtype=np.float32)
        # A second model on the same env whose averaged actor runs in bfloat16 (its own buffer and pending actions)
        bf16_model = CGAC("MlpPolicy", env, seed=0, device="cpu")
        # Collection only calls the averaged actor's sample(), which the stand-in provides
        bf16_model.actor_avg = BFloat16Sampler(bf16_model.actor_avg)  # type: ignore[assignment]
        self.functions = {
            "raw": self.raw,
            "bare loop": self.bare,
            "CGAC collection": self.collection(model),
            "CGAC collection, bfloat16 forward": self.collection(bf16_model),
        }
        self.env_seconds = dict.fromkeys(self.functions, 0.0)
        self.env_calls = dict.fromkeys(self.functions, 0)

    def raw(self) -> None:
        self.calls += 1
        self.env.step(self.actions[self.calls % len(self.actions)])

    def bare(self) -> None:
        obs, rewards, dones, _ = self.env.step(self.pending)
        self.calls += 1
        pos = self.calls % len(self.obs_store)
        self.obs_store[pos] = obs
        with th.inference_mode():
            draws = self.model.actor_avg.sample(th.from_numpy(self.obs_store[pos]), 2).numpy()
        self.action_store[pos], self.reward_store[pos], self.done_store[pos] = self.pending, rewards, dones
        self.pending = draws[0]

    def collection(self, model: CGAC) -> Callable[[], None]:
        """One step of ``model``'s real collection, on this env."""
        _, callback = model._setup_learn(10**12)
        callback.on_training_start({}, {})

        def collect() -> None:
            model.collect_rollouts(self.env, callback, model.rollout_buffer, n_rollout_steps=1)

        return collect

    def timed(self) -> dict[str, Callable[[], None]]:
        """The loops, each adding its env-step time to ``env_seconds``."""

        def timed_function(name: str) -> Callable[[], None]:
            def step() -> None:
                start = self.env.seconds
                self.functions[name]()
                self.env_seconds[name] += self.env.seconds - start
                self.env_calls[name] += 1

            return step

        return {name: timed_function(name) for name in self.functions}


class EnvPoolLoops:
    """Part 3: loops over envpool's own API (no adapter, no buffer), each run for a chunk of time."""

    def __init__(self, model: CGAC, env_id: str, n_envs: int, num_threads: int, pin_offset: int):
        import envpool

        self.actor = model.actor_avg
        self.pool = envpool.make_gymnasium(env_id, num_envs=n_envs, num_threads=num_threads, seed=0)
        # The same pool with its worker threads pinned to one core each (envpool pins thread i to core offset + i)
        self.pinned_pool = envpool.make_gymnasium(
            env_id, num_envs=n_envs, num_threads=num_threads, seed=0, thread_affinity_offset=pin_offset
        )
        self.async_pool = envpool.make_gymnasium(
            env_id, num_envs=n_envs, batch_size=n_envs // 2, num_threads=num_threads, seed=1
        )
        # All actions sent at once, results taken in two halves as they finish: the envs stay in step
        self.halves_pool = envpool.make_gymnasium(
            env_id, num_envs=n_envs, batch_size=n_envs // 2, num_threads=num_threads, seed=2
        )
        action_shape = self.pool.action_space.shape
        self.uniform = np.random.default_rng(0).uniform(-1, 1, (16, n_envs, *action_shape)).astype(np.float32)
        self.obs = self.pool.reset()[0]
        self.pinned_obs = self.pinned_pool.reset()[0]
        self.policy_bank = np.stack([self.step_with_actor() for _ in range(16)])  # actions met along the way
        self.async_pool.async_reset()
        self.halves_pool.async_reset()
        self.halves_actions = np.zeros((n_envs, *action_shape), dtype=np.float32)
        for _ in range(2):
            obs, *_, info = self.halves_pool.recv()
            self.halves_actions[info["env_id"]] = self.actions(obs)
        self.step_counts = np.zeros(n_envs, dtype=np.int64)
        self.pending: list[tuple[np.ndarray, np.ndarray]] = []
        self.calls = 0

    def actions(self, obs: np.ndarray) -> np.ndarray:
        with th.inference_mode():
            return self.actor.sample(th.as_tensor(obs, dtype=th.float32), 2)[0].numpy()

    def step_with_actor(self) -> np.ndarray:
        actions = self.actions(self.obs)
        self.obs = self.pool.step(actions)[0]
        return actions

    def step_pinned_with_actor(self) -> None:
        self.pinned_obs = self.pinned_pool.step(self.actions(self.pinned_obs))[0]

    def run(self, loop: str, seconds: float) -> int:
        """Env steps done by ``loop`` in ``seconds``."""
        if loop == "async":
            return self.run_async(seconds)
        if loop == "in step: send all, recv halves":
            return self.run_halves(seconds)
        end, steps = time.perf_counter() + seconds, 0
        while time.perf_counter() < end:
            self.calls += 1
            if loop == "raw, uniform actions":
                self.pool.step(self.uniform[self.calls % 16])
            elif loop == "raw, the actor's actions":
                self.pool.step(self.policy_bank[self.calls % 16])
            elif loop == "raw, uniform actions, pinned threads":
                self.pinned_pool.step(self.uniform[self.calls % 16])
            elif loop == "sync: step, forward, pinned threads":
                self.step_pinned_with_actor()
            else:
                self.step_with_actor()
            steps += len(self.obs)
        return steps

    def run_halves(self, seconds: float) -> int:
        """Every env steps once per round; the first half's forward pass overlaps the rest's simulation."""
        end, steps = time.perf_counter() + seconds, 0
        threads = th.get_num_threads()
        th.set_num_threads(1)
        all_envs = np.arange(len(self.halves_actions), dtype=np.int32)
        while time.perf_counter() < end:
            self.halves_pool.send(self.halves_actions, all_envs)
            for _ in range(2):
                obs, *_, info = self.halves_pool.recv()
                self.halves_actions[info["env_id"]] = self.actions(obs)
            steps += len(all_envs)
        th.set_num_threads(threads)
        return steps

    def run_async(self, seconds: float) -> int:
        """The asynchronous loop: two halves in flight; at the end it drains them, so no env steps behind it."""
        end, steps = time.perf_counter() + seconds, 0
        threads = th.get_num_threads()
        th.set_num_threads(1)  # the other core simulates meanwhile
        for actions, env_ids in self.pending:
            self.async_pool.send(actions, env_ids)
        in_flight, self.pending = len(self.pending) or 2, []  # 2: both halves, from async_reset
        while in_flight:
            obs, *_, info = self.async_pool.recv()
            env_ids = info["env_id"]
            self.step_counts[env_ids] += 1
            steps += len(env_ids)
            if time.perf_counter() < end:
                self.async_pool.send(self.actions(obs), env_ids)
            else:  # keep the actions for the next chunk
                self.pending.append((self.actions(obs), env_ids))
                in_flight -= 1
        th.set_num_threads(threads)
        return steps


def envpool_loops(model: CGAC, env_id: str, n_envs: int, seconds: float, chunk: float) -> None:
    num_threads = min(os.cpu_count() or 1, n_envs // 2)
    # Pin to the first cores this process may use (envpool pins thread i to core offset + i)
    pin_offset = min(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 0
    loops = EnvPoolLoops(model, env_id, n_envs, num_threads, pin_offset)
    names = ["raw, uniform actions", "raw, the actor's actions", "sync: step, forward"]
    names += ["in step: send all, recv halves", "async"]
    names += ["raw, uniform actions, pinned threads", "sync: step, forward, pinned threads"]
    steps = dict.fromkeys(names, 0)
    elapsed = dict.fromkeys(names, 0.0)
    for name in names:  # warm-up
        loops.run(name, chunk)
    loops.step_counts[:] = 0
    while min(elapsed.values()) < seconds:
        for name in names:
            start = time.perf_counter()
            steps[name] += loops.run(name, chunk)
            elapsed[name] += time.perf_counter() - start
    raw = steps[names[0]] / elapsed[names[0]]
    for name in names:
        rate = steps[name] / elapsed[name]
        print(f"   {name}: {rate:,.0f} ({rate / raw:.0%} of raw)")
    drift = loops.step_counts.max() - loops.step_counts.min()
    print(f"   async: the envs' step counts spread over {drift} steps (the on-policy window needs 0)")
    pinned = steps[names[-1]] / elapsed[names[-1]] / (steps[names[-2]] / elapsed[names[-2]])
    print(f"   pinned threads (thread_affinity_offset={pin_offset}): sync loop at {pinned:.0%} of pinned raw")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="HalfCheetah-v5")
    parser.add_argument("--n-envs", type=int, default=256)
    parser.add_argument("--backend", default="envpool")
    parser.add_argument("--calls", type=int, default=500, help="forward passes per timing of part 1")
    parser.add_argument("--seconds", type=float, default=6.0, help="measuring time of each loop in parts 2 and 3")
    parser.add_argument("--chunk", type=float, default=0.1, help="the loops alternate in chunks of this length")
    args = parser.parse_args()

    env = make_vec_env(args.env, n_envs=args.n_envs, backend=args.backend, seed=0)
    model = CGAC("MlpPolicy", env, seed=0, device="cpu")  # the profile is of CPU inference, also where a GPU exists
    action_shape = env.action_space.shape or ()
    actions = np.random.default_rng(0).uniform(-1, 1, (16, env.num_envs, *action_shape)).astype(np.float32)
    print(f"{args.env}, {args.n_envs} envs, {args.backend} backend, {th.get_num_threads()} torch threads")

    print("1. averaged-actor forward pass (two draws) and 20 small torch ops, median ms:")
    for name, seconds in forward_timings(model, env, actions, args.calls).items():
        print(f"   {name}: {seconds * 1e3:.3f}")

    print(f"2. steps/s, alternating in {args.chunk:g}-s chunks, {args.seconds:g} s each:")
    loops = StepFunctions(model, env, actions)
    alternate(loops.timed(), env.num_envs, 0.5, args.chunk)  # warm-up
    loops.env_seconds, loops.env_calls = dict.fromkeys(loops.functions, 0.0), dict.fromkeys(loops.functions, 0)
    rates = alternate(loops.timed(), env.num_envs, args.seconds, args.chunk)
    for name, rate in rates.items():
        print(f"   {name}: {rate:,.0f} ({rate / rates['raw']:.0%} of raw)")
    print("   mean ms per env step inside each loop, in the same chunks:")
    for name in rates:
        print(f"   env step in {name}: {loops.env_seconds[name] / loops.env_calls[name] * 1e3:.3f}")
    if args.backend == "envpool" and args.n_envs % 2 == 1:
        print("3. envpool's own API: skipped, the asynchronous loop steps half the envs at a time (needs an even --n-envs)")
    elif args.backend == "envpool":
        print(f"3. envpool's own API, steps/s, alternating in {args.chunk:g}-s chunks, {args.seconds:g} s each:")
        envpool_loops(model, args.env, args.n_envs, args.seconds, args.chunk)
    env.close()


if __name__ == "__main__":
    main()
