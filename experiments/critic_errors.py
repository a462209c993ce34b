"""
Where the critics' large errors sit while a run trains on HalfCheetah-v5: every ``--every`` iterations, over the
critic minibatches of one iteration, the median, 90th and 99th percentile and maximum of ``|Q - target|`` (the first
critic against the Q-GAE targets, paper Eq. 8-10), and for the largest 1% of them against the whole minibatch: the
mean target and Q, the root's pitch angle ``|obs[1]|`` and forward velocity ``obs[8]``, and the share of flipped
states (``|pitch| > 1.5``). The run is the named YAML entry's, as ``python -m sb3_cgac.compare`` builds it, so that a
screen's seed is retraced (the one-setting screen's falls, docs/tuning.md)::

    python experiments/critic_errors.py --conf docs/results/one-setting-screen/conf/cgac_one12.yml --stop 420000
    python experiments/critic_errors.py --conf docs/results/one-setting-screen/conf/cgac_one10.yml --start 800000 \\
        --stop 900000
"""

import argparse

from sb3_cgac.threads import configure_thread_spin

configure_thread_spin()

import numpy as np  # noqa: E402
import torch as th  # noqa: E402
from stable_baselines3.common.callbacks import BaseCallback  # noqa: E402

import sb3_cgac.cgac  # noqa: E402
from sb3_cgac.zoo import build_model  # noqa: E402

# HalfCheetah-v5's observation: qpos[1:] (rootz, rooty, 6 joints), then qvel (rootx velocity first)
PITCH, FORWARD_VELOCITY = 1, 8
FLIPPED_PITCH = 1.5


class CriticErrors(BaseCallback):
    """Records the critics' minibatch errors during every ``every``-th iteration from step ``start`` and prints them."""

    def __init__(self, start: int, stop: int, every: int):
        super().__init__()
        self.start, self.stop, self.every = start, stop, every
        self.recording = False
        self.batches: list[tuple[th.Tensor, ...]] = []
        self.original_loss = sb3_cgac.cgac.critic_loss

    def _on_training_start(self) -> None:
        def recording_loss(critic, observations, actions, returns, weights, *args, **kwargs):  # type: ignore[no-untyped-def]
            if self.recording:
                with th.no_grad():
                    q_values = critic.q_values(observations, actions)[0]
                    kept = weights > 0
                    errors = (q_values - returns).abs()[kept]
                    pitch, velocity = observations[kept, PITCH].abs(), observations[kept, FORWARD_VELOCITY]
                    self.batches.append((errors, returns[kept], q_values[kept], pitch, velocity))
            return self.original_loss(critic, observations, actions, returns, weights, *args, **kwargs)

        sb3_cgac.cgac.critic_loss = recording_loss  # type: ignore[assignment]

    def _on_training_end(self) -> None:
        sb3_cgac.cgac.critic_loss = self.original_loss

    def _on_rollout_start(self) -> None:
        # The updates that follow a rollout run after its end: print those of the last iteration, then decide for the next
        self._print_row()
        iteration = self.model.num_timesteps // self.model.n_envs
        self.recording = self.model.num_timesteps >= self.start and (iteration + 1) % self.every == 0

    def _print_row(self) -> None:
        if not self.batches:
            return
        errors, targets, q_values, pitch, velocity = (th.cat(columns) for columns in zip(*self.batches, strict=True))
        self.batches.clear()
        top = errors.topk(max(1, len(errors) // 100)).indices
        quantiles = th.quantile(errors, th.tensor([0.5, 0.9, 0.99])).tolist()
        episodes = list(self.model.ep_info_buffer or [])
        episode_return = np.mean([episode["r"] for episode in episodes]) if episodes else np.nan
        print(
            f"| {self.model.num_timesteps} | {quantiles[0]:.4f} | {quantiles[1]:.4f} | {quantiles[2]:.4f} "
            f"| {errors.max():.3f} "
            f"| {targets[top].mean():.2f} / {targets.mean():.2f} | {q_values[top].mean():.2f} "
            f"| {pitch[top].mean():.2f} / {pitch.mean():.2f} | {velocity[top].mean():.2f} / {velocity.mean():.2f} "
            f"| {(pitch[top] > FLIPPED_PITCH).float().mean():.2f} / {(pitch > FLIPPED_PITCH).float().mean():.3f} "
            f"| {episode_return:.4g} |",
            flush=True,
        )

    def _on_step(self) -> bool:
        return self.model.num_timesteps < self.stop


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="HalfCheetah-v5")
    parser.add_argument("--conf", required=True, help="YAML file whose entry for --env is trained")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--start", type=int, default=0, help="env steps before the first row")
    parser.add_argument("--stop", type=int, required=True, help="env steps at which training stops")
    parser.add_argument("--every", type=int, default=50, help="iterations between rows")
    args = parser.parse_args(argv)

    th.set_num_threads(1)  # one core for the updates, the other for envpool's thread
    model, manager = build_model(
        "cgac",
        args.env,
        seed=args.seed,
        backend="envpool",
        backend_kwargs=dict(num_threads=1),
        log_folder="/tmp/critic_errors",
        conf_file=args.conf,
    )
    print(
        "| steps | median | 90% | 99% | max | target: top 1% / all | Q: top 1% | pitch: top 1% / all | forward velocity: "
        "top 1% / all | flipped: top 1% / all | episode return |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    callback = CriticErrors(args.start, args.stop, args.every)
    model.learn(manager.n_timesteps, callback=[callback, *(manager.callbacks or [])])


if __name__ == "__main__":
    main()
