"""
One rank of the data-parallel tests (tests/test_distributed.py starts two with torchrun on gloo).

    python -m torch.distributed.run --standalone --nproc-per-node 2 tests/distributed_worker.py <check> <folder>
"""

import copy
import json
import sys
from pathlib import Path

import torch as th
import torch.distributed as dist
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize

from sb3_cgac import CGAC
from sb3_cgac.buffers import CGACSamples
from sb3_cgac.common.distributed import DataParallel, init_from_env, leave
from sb3_cgac.losses import critic_loss


class FailAt(BaseCallback):
    """Rank 1 fails after a few steps."""

    def __init__(self, rank: int):
        super().__init__()
        self.rank = rank

    def _on_step(self) -> bool:
        if self.rank == 1 and self.num_timesteps >= 8 * 20:
            raise RuntimeError("rank 1 fails on purpose")
        return True


# The critic options, for the checks named "<check>-critic-options"
CRITIC_OPTIONS = dict(critic_layer_norm=True, n_bins=21, actor_q_reduction="mean")


def small_model(critic_options: bool = False) -> CGAC:
    env = make_vec_env("Pendulum-v1", n_envs=8)
    policy_kwargs = dict(net_arch=[32, 32], normalize_observations=True, **(CRITIC_OPTIONS if critic_options else {}))
    return CGAC("MlpPolicy", env, batch_size=64, n_steps=2, scale_rewards=True, policy_kwargs=policy_kwargs, seed=0)


def flat_state(model: CGAC) -> th.Tensor:
    """Every parameter and buffer of the policy (normaliser statistics included), and log(alpha)."""
    tensors = [value.detach().reshape(-1).double() for value in model.policy.state_dict().values()]
    return th.cat([*tensors, model.log_ent_coef.detach().reshape(-1).double()])


def main() -> None:
    check, folder = sys.argv[1], Path(sys.argv[2])
    critic_options = check.endswith("-critic-options")
    check = check.removesuffix("-critic-options")
    rank, world_size = init_from_env(timeout_s=60)
    model = small_model(critic_options)
    result: dict = {"rank": rank, "world_size": world_size}
    if check == "train":
        model.learn(8 * 60)
        states = [th.zeros_like(flat_state(model)) for _ in range(world_size)]
        dist.all_gather(states, flat_state(model))
        first_obs = [th.zeros(8, 3) for _ in range(world_size)]
        dist.all_gather(first_obs, th.as_tensor(model.get_env().reset(), dtype=th.float32))
        result["identical"] = all(th.equal(states[0], state) for state in states)
        result["envs_differ"] = not th.equal(first_obs[0], first_obs[1])
        # The normaliser merged the rows of both ranks: 8 envs x (60 steps + the first observation) each
        result["normalizer_count"] = float(model.policy.obs_normalizer.count)
        result["num_timesteps"] = model.num_timesteps
        # The reward scale merged the returns of both ranks: 8 envs x 60 steps each, one divisor on every rank
        assert model.return_scale is not None
        result["return_count"] = float(model.return_scale.statistics.count)
        result["reward_scale"] = float(model.return_scale.scale())
        if rank == 0:
            model.save(folder / "model")
            # Loaded on rank 0 alone (to evaluate) it waits for no other rank
            loaded = CGAC.load(folder / "model", env=make_vec_env("Pendulum-v1", n_envs=8))
            result["loaded_predicts"] = bool(th.isfinite(th.as_tensor(loaded.predict(th.zeros(8, 3).numpy())[0])).all())
    elif check == "gradients":
        model.learn(8 * 20)  # fill the window; then one critic gradient on each rank's own minibatch
        parallel = DataParallel(model.device)
        data = model.rollout_buffer.sample(model.batch_size)
        reference = copy.deepcopy(model.critic)  # the same parameters on both ranks, before the update
        loss, _ = critic_loss(model.critic, *data, data.weights.sum().clamp_min(1.0), None, parallel.gather)
        model.critic.zero_grad()
        loss.backward()
        parallel.average_gradients(list(model.critic.parameters()))
        averaged = th.cat([param.grad.reshape(-1) for param in model.critic.parameters()])
        # One process that sees both ranks' minibatches
        gathered = []
        for tensor in data:  # a Box observation: every field is a tensor
            parts = [th.zeros_like(tensor) for _ in range(world_size)]
            dist.all_gather(parts, tensor.contiguous())
            gathered.append(th.cat(parts))
        union = CGACSamples(*gathered)
        loss, _ = critic_loss(reference, *union, union.weights.sum().clamp_min(1.0), None)
        reference.zero_grad()
        loss.backward()
        single = th.cat([param.grad.reshape(-1) for param in reference.parameters()])
        result["max_gap"] = float((averaged - single).abs().max())
        result["scale"] = float(single.abs().max())
        result["minibatches_differ"] = not th.equal(gathered[0][: model.batch_size], gathered[0][model.batch_size :])
    elif check == "vecnormalize":
        env = VecNormalize(make_vec_env("Pendulum-v1", n_envs=8), norm_reward=False)
        model = CGAC("MlpPolicy", env, batch_size=64, n_steps=2, policy_kwargs=dict(net_arch=[32, 32]), seed=0)
        model.learn(8 * 20)
        rms = env.obs_rms
        statistics = th.as_tensor([rms.count, *rms.mean, *rms.var], dtype=th.float64)
        gathered = [th.zeros_like(statistics) for _ in range(world_size)]
        dist.all_gather(gathered, statistics)
        result["identical"] = all(th.equal(gathered[0], found) for found in gathered)
        result["count"] = float(rms.count)
    elif check == "fail":
        model.learn(8 * 200, callback=FailAt(rank))
    (folder / f"rank{rank}.json").write_text(json.dumps(result))
    leave()


if __name__ == "__main__":
    main()
