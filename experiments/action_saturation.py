"""
How saturated CGAC's actions become while an entry trains: every ``--every`` iterations, the actor's std, the share of
deterministic actions ``tanh(mean)`` beyond 0.9 and 0.99 in magnitude on the envs' current observations, the mean
magnitude of the pre-tanh means, alpha, the entropy and its target, and the training episodes' mean length and return;
at the end, per action dimension, the mean deterministic action, its share beyond 0.99, the actor's std and the
critics' gradient at the deterministic actions (dQ/da, and dQ/du before the tanh)::

    python experiments/action_saturation.py --env Go1JoystickFlatTerrain-v1 --minutes 10
    python experiments/action_saturation.py --env MuJoCoPlayground/LeapCubeReorient-v1 --params learning_rate=0.0003

``--probe`` then asks whether the critics' push on each dimension whose deterministic action averages at least 0.5
in magnitude (or on each one named) is right: the critics' minimum Q at the envs' current observations with that
dimension set to -1, -0.5, 0, 0.5 and 1 (the other dimensions deterministic: a change at one step), beside the mean
return of whole evaluation episodes of the deterministic policy with that dimension held at the same value (one
episode per env of an evaluation env built as the entry builds it).

``--gaussian-entropy`` screens an entropy target on the Gaussian before the tanh: alpha's update (paper Eq. 12) reads
the pre-tanh log-probability, the actor's loss (Eq. 7) is unchanged.
"""

import argparse
import ast
import time

from sb3_cgac.threads import configure_thread_spin

configure_thread_spin()

import numpy as np  # noqa: E402
import torch as th  # noqa: E402
from stable_baselines3.common.logger import configure  # noqa: E402
from stable_baselines3.common.vec_env import VecEnv, sync_envs_normalization  # noqa: E402

import sb3_cgac.cgac  # noqa: E402
from sb3_cgac import CGAC  # noqa: E402
from sb3_cgac.policies import TANH_EPSILON  # noqa: E402
from sb3_cgac.zoo import build_model  # noqa: E402

PROBE_VALUES = (-1.0, -0.5, 0.0, 0.5, 1.0)


def gaussian_entropy_actor_loss(
    actor, critic, observations, weights, weight_sum, ent_coef, autocast_dtype=None, q_reduction="min"
):  # type: ignore[no-untyped-def]
    """``losses.actor_loss`` in float32, returning the pre-tanh log-probability (what alpha's update reads) instead."""
    actions, log_prob = actor.action_log_prob(observations)
    q_values = critic.q_values(observations, actions)
    q_value = q_values.min(dim=0).values if q_reduction == "min" else q_values.mean(dim=0)
    loss = ((ent_coef * log_prob - q_value) * weights).sum() / weight_sum
    return loss, (log_prob + th.log(1 - actions**2 + TANH_EPSILON).sum(dim=1)).detach()


def episode_returns(model: CGAC, env: VecEnv, dimension: int | None, value: float) -> tuple[float, float]:
    """Mean return and length of the first episode of every env of ``env``, acting with ``predict(deterministic=True)``
    and, if ``dimension`` is given, that squashed action dimension held at ``value``."""
    observations = env.reset()
    returns, lengths = np.zeros(env.num_envs), np.zeros(env.num_envs)
    running = np.ones(env.num_envs, dtype=bool)
    while running.any():
        actions, _ = model.predict(observations, deterministic=True)  # type: ignore[arg-type]
        if dimension is not None:
            actions[:, dimension] = model.policy.unscale_action(np.full_like(actions, value))[:, dimension]
        observations, rewards, dones, _ = env.step(actions)
        returns += rewards * running
        lengths += running
        running &= ~dones
    return float(returns.mean()), float(lengths.mean())


def probe(model: CGAC, manager, observations, dimensions: list[int], n_envs: int) -> None:  # type: ignore[no-untyped-def]
    """The critics' Q and the real return with one saturated dimension held at each of ``PROBE_VALUES``."""
    env = manager.create_envs(n_envs, eval_env=True, no_log=True)
    train_env = model.get_env()
    if model.get_vec_normalize_env() is not None and train_env is not None:
        sync_envs_normalization(train_env, env)
    base_return, base_length = episode_returns(model, env, None, 0.0)
    print(f"\nDeterministic policy, {n_envs} evaluation episodes: return {base_return:.4g}, length {base_length:.0f}")
    print("\n| dimension | held at | critics' min Q (mean) | return (mean) | episode length |")
    print("| --- | --- | --- | --- | --- |")
    with th.no_grad():
        deterministic = model.policy.actor_avg(observations, deterministic=True)
        for dimension in dimensions:
            for value in PROBE_VALUES:
                actions = deterministic.clone()
                actions[:, dimension] = value
                q = model.critic.q_values(observations, actions).min(dim=0).values.mean()
                episode_return, length = episode_returns(model, env, dimension, value)
                print(f"| {dimension} | {value:+.1f} | {q:.4g} | {episode_return:.4g} | {length:.0f} |", flush=True)
    env.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Go1JoystickFlatTerrain-v1")
    parser.add_argument("--backend", default="envpool")
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--every", type=int, default=400, help="iterations (env steps of all envs) between rows")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--params", nargs="*", default=[], help="overrides of the entry, as key=value (Python literals)")
    parser.add_argument("--gaussian-entropy", action="store_true")
    parser.add_argument(
        "--probe", nargs="*", type=int, help="hold these action dimensions (none named: the large ones) at fixed values"
    )
    parser.add_argument("--probe-envs", type=int, default=64, help="evaluation envs (one episode each) per probe")
    parser.add_argument("--log-folder", default="/tmp/action_saturation", help="where the zoo writes the run's config")
    args = parser.parse_args()

    th.set_num_threads(1)  # one core for the updates, the other for envpool's thread

    if args.gaussian_entropy:
        sb3_cgac.cgac.actor_loss = gaussian_entropy_actor_loss  # type: ignore[assignment]
    overrides = {key: ast.literal_eval(value) for key, value in (item.split("=", 1) for item in args.params)}
    model, manager = build_model(
        "cgac",
        args.env,
        seed=args.seed,
        backend=args.backend,
        backend_kwargs=dict(num_threads=1),
        log_folder=args.log_folder,
        hyperparams=overrides,
    )
    assert isinstance(model, CGAC)
    model.set_logger(configure(None, []))
    print(
        "| steps | seconds | std | abs(a) > 0.9 | abs(a) > 0.99 | abs(pre-tanh mean) | alpha | entropy | target | "
        "episode length | return |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    start = time.perf_counter()
    while time.perf_counter() - start < args.minutes * 60:
        model.learn(model.n_envs * args.every, reset_num_timesteps=False, callback=manager.callbacks)
        observations, _ = model.policy.obs_to_tensor(model._last_obs)  # type: ignore[arg-type]
        with th.no_grad():
            mean, log_std = model.actor.get_action_dist_params(observations)
        actions = th.tanh(mean).abs()
        logged = model.logger.name_to_value
        episodes = list(model.ep_info_buffer or [])
        length = np.mean([episode["l"] for episode in episodes]) if episodes else np.nan
        episode_return = np.mean([episode["r"] for episode in episodes]) if episodes else np.nan
        print(
            f"| {model.num_timesteps} | {time.perf_counter() - start:.0f} | {log_std.exp().mean():.3f} "
            f"| {(actions > 0.9).float().mean():.2f} | {(actions > 0.99).float().mean():.2f} | {mean.abs().mean():.2f} "
            f"| {logged.get('train/ent_coef', np.nan):.2g} | {logged.get('train/entropy', np.nan):.1f} "
            f"| {logged.get('train/target_entropy', np.nan):.0f} | {length:.0f} | {episode_return:.3g} |",
            flush=True,
        )
    # Which dimensions saturate, to which side, and how hard the critics pull them there: the gradient of the minimum
    # of the critics at the deterministic actions (the actor loss's, paper Eq. 7, without the entropy term), dQ/da, and
    # through the tanh, dQ/du (the last row's observations)
    deterministic = th.tanh(mean).requires_grad_(True)
    min_q = model.critic.q_values(observations, deterministic).min(dim=0).values
    (dq_da,) = th.autograd.grad(min_q.sum(), deterministic)
    dq_du = dq_da * (1 - deterministic.detach() ** 2)
    print("\n| dimension | mean action | abs(a) > 0.99 | std | dQ/da | dQ/du |\n| --- | --- | --- | --- | --- | --- |")
    stds = log_std.exp().expand_as(mean).mean(dim=0)
    saturated = (actions > 0.99).float().mean(dim=0)
    columns = (deterministic.detach().mean(dim=0), saturated, stds, dq_da.mean(dim=0), dq_du.mean(dim=0))
    for dimension, (mean_action, share, std, da, du) in enumerate(zip(*columns, strict=True)):
        print(f"| {dimension} | {mean_action:+.2f} | {share:.2f} | {std:.3f} | {da:+.3g} | {du:+.3g} |")
    if args.probe is not None:
        dimensions = args.probe or [int(d) for d in th.nonzero(actions.mean(dim=0) >= 0.5).flatten()]
        probe(model, manager, observations, dimensions, args.probe_envs)


if __name__ == "__main__":
    main()
