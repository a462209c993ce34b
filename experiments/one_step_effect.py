"""
What changing one action at one step really does, against what CGAC's critics say it does: trains the CGAC entry of an
envpool port of a MuJoCo Playground task for ``--minutes``, then, in Playground's own JAX version of the task (whose
states can be copied), runs the deterministic policy ``--start`` steps in ``--states`` envs, and from those states
branches: at the first step one action dimension is set to -1, -0.5, 0, 0.5 or 1 (or left as the policy's), then the
policy acts for ``--horizon`` steps. Per branch it prints the critics' minimum Q of that first action and the mean
discounted return of the branch (every branch of a state shares its random numbers)::

    python experiments/one_step_effect.py --env MuJoCoPlayground/LeapCubeReorient-v1 --task LeapCubeReorient --dims 2 4

Needs the ``playground`` extra and envpool's asset packages (the robots' models, ``use_menagerie``).
"""

import argparse
import time
from typing import Any

from sb3_cgac.threads import configure_thread_spin

configure_thread_spin()

import jax  # noqa: E402
import jax.numpy as jp  # noqa: E402
import numpy as np  # noqa: E402
import torch as th  # noqa: E402
from mujoco_playground import registry  # noqa: E402

from sb3_cgac import CGAC  # noqa: E402
from sb3_cgac.vec_env.playground_vec_env import use_menagerie  # noqa: E402
from sb3_cgac.zoo import build_model  # noqa: E402

VALUES = (None, -1.0, -0.5, 0.0, 0.5, 1.0)  # None: the policy's own action


def allow_clip_a_max() -> None:
    """Playground 0.2.0's LeapCubeReorient calls ``jnp.clip(a_max=...)``, which JAX 0.10 rejects: accept the old names
    in this process only (the library raises an error for it instead)."""
    clip = jp.clip

    def compatible_clip(x: Any, min: Any = None, max: Any = None, a_min: Any = None, a_max: Any = None) -> Any:
        return clip(x, a_min if min is None else min, a_max if max is None else max)

    jp.clip = compatible_clip  # type: ignore[assignment]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="MuJoCoPlayground/LeapCubeReorient-v1", help="the envpool port to train on")
    parser.add_argument("--task", default="LeapCubeReorient", help="the same task in mujoco_playground's registry")
    parser.add_argument("--minutes", type=float, default=4.0)
    parser.add_argument("--n-envs", type=int, help="training envs (default: the entry's)")
    parser.add_argument("--dims", type=int, nargs="+", default=[0])
    parser.add_argument("--states", type=int, default=16, help="start states (envs of the JAX version)")
    parser.add_argument("--start", type=int, default=50, help="policy steps before the branches")
    parser.add_argument("--horizon", type=int, default=150, help="steps of each branch")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--log-folder", default="/tmp/one_step_effect", help="where the zoo writes the run's config")
    args = parser.parse_args()

    th.set_num_threads(1)
    model, manager = build_model(
        "cgac",
        args.env,
        seed=args.seed,
        backend="envpool",
        backend_kwargs=dict(num_threads=1),
        log_folder=args.log_folder,
        hyperparams=None if args.n_envs is None else {"n_envs": args.n_envs},
    )
    assert isinstance(model, CGAC)
    start = time.perf_counter()
    while time.perf_counter() - start < args.minutes * 60:
        model.learn(model.n_envs * 200, reset_num_timesteps=False, callback=manager.callbacks)
    gamma = model.gamma

    allow_clip_a_max()
    use_menagerie()
    env = registry.load(args.task, config_overrides={"impl": "jax"})
    reset, step = jax.jit(jax.vmap(env.reset)), jax.jit(jax.vmap(env.step))

    def act(observations: Any, override: tuple[int, float] | None = None) -> tuple[th.Tensor, Any]:
        if isinstance(observations, dict):
            tensors: Any = {key: th.as_tensor(np.asarray(value)) for key, value in observations.items()}
        else:
            tensors = th.as_tensor(np.asarray(observations))
        with th.no_grad():
            actions = model.policy.actor_avg(tensors, deterministic=True)
        if override is not None:
            actions[:, override[0]] = override[1]
        return actions, tensors

    def run(state: Any, alive: np.ndarray, first: th.Tensor | None, steps: int) -> tuple[Any, np.ndarray, np.ndarray]:
        """``steps`` policy steps (the first one's actions given) from ``state``: the end state, who is alive, the
        discounted returns."""
        returns, discount, alive = np.zeros(len(alive)), 1.0, alive.copy()
        for index in range(steps):
            actions = first if index == 0 and first is not None else act(state.obs)[0]
            state = step(state, jp.asarray(actions.numpy()))
            returns += discount * np.asarray(state.reward) * alive
            alive &= np.asarray(state.done) == 0
            discount *= gamma
        return state, alive, returns

    state = reset(jax.random.split(jax.random.PRNGKey(args.seed), args.states))
    state, alive, _ = run(state, np.ones(args.states, dtype=bool), None, args.start)
    print(f"{args.env}: {model.num_timesteps} steps of training; {alive.sum()} of {args.states} envs of {args.task} "
          f"(JAX) still in their episode after {args.start} steps")  # fmt: skip
    print(f"\n| dimension | first action | critics' min Q | discounted return over {args.horizon} steps | difference |")
    print("| --- | --- | --- | --- | --- |")
    for dimension in args.dims:
        baseline = None
        for value in VALUES:
            first, tensors = act(state.obs, None if value is None else (dimension, value))
            with th.no_grad():
                q = model.critic.q_values(tensors, first).min(dim=0).values.numpy()
            returns = run(state, alive, first, args.horizon)[2]
            baseline = returns if value is None else baseline
            assert baseline is not None
            difference = returns[alive] - baseline[alive]  # paired: the same state and random numbers
            label = "the policy's" if value is None else f"{value:+.1f}"
            print(
                f"| {dimension} | {label} | {q[alive].mean():.4g} | {returns[alive].mean():.4g} "
                f"| {difference.mean():+.3g} +/- {difference.std() / np.sqrt(alive.sum()):.2g} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
