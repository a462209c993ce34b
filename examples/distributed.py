"""
Data-parallel CGAC with torch.distributed: every rank (process) steps its own envs into its own window, and every
update averages the gradients of all ranks, so that they hold identical parameters. Rank 0 logs and saves.

    torchrun --nproc-per-node 2 examples/distributed.py --env HalfCheetah-v5 --backend envpool --timesteps 2000000
    python examples/distributed.py --env Pendulum-v1 --timesteps 100000          # the same script, one process

``--n-envs`` is per rank; ``--timesteps`` counts the env steps of all ranks. Several machines: run torchrun on each
with ``--nnodes N --node-rank <i> --rdzv-backend c10d --rdzv-endpoint <host of node 0>:29500``; on GPUs the ranks
use NCCL (``NCCL_SOCKET_IFNAME`` names the network interface when a node has several).
"""

import argparse

from sb3_cgac.threads import configure_thread_spin

configure_thread_spin()  # before anything imports torch (envpool's threads)

from sb3_cgac import CGAC  # noqa: E402
from sb3_cgac.common.distributed import init_from_env, leave  # noqa: E402
from sb3_cgac.vec_env import make_vec_env  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Pendulum-v1")
    parser.add_argument("--timesteps", type=int, default=100_000, help="env steps of all ranks together")
    parser.add_argument("--n-envs", type=int, default=64, help="envs of each rank")
    parser.add_argument("--backend", default="dummy", help="vec-env backend (envpool for MuJoCo)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", default="cgac_distributed")
    args = parser.parse_args()

    rank, world_size = init_from_env()  # gloo on CPUs, NCCL on GPUs; (0, 1) without torchrun
    env = make_vec_env(args.env, n_envs=args.n_envs, backend=args.backend)
    # The model gives each rank its own seed (seed + rank * 1,000,000): its envs and minibatches differ
    policy_kwargs = dict(normalize_observations=True)  # statistics of every rank's observations
    model = CGAC("MlpPolicy", env, policy_kwargs=policy_kwargs, seed=args.seed, verbose=1 if rank == 0 else 0)
    model.learn(args.timesteps // world_size)
    if rank == 0:
        model.save(args.output)
        print(f"{world_size} rank(s) trained {model.num_timesteps * world_size} steps in all; saved {args.output}.zip")
    leave()  # under torchrun: wait for every rank, then end the process group and this process


if __name__ == "__main__":
    main()
