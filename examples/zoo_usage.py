"""
The rl-zoo entries of this package from Python (``pip install -e ".[zoo,envpool]"``): build a model exactly as
``python -m sb3_cgac.train --algo cgac --env <id>`` does, train it, and save it with its ``VecNormalize`` statistics.

    python examples/zoo_usage.py [--env Hopper-v5] [--timesteps 200000]

From the shell the same entry trains with ``python -m sb3_cgac.train --algo cgac --env Hopper-v5 --vec-env envpool``
(every rl_zoo3 flag works) and plays with ``python -m sb3_cgac.enjoy --algo cgac --env Hopper-v5 -f logs/``.
"""

import argparse
import tempfile
from pathlib import Path

from sb3_cgac.zoo import build_model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--timesteps", type=int, default=200_000)
    parser.add_argument("--backend", default="envpool", help="vec-env backend: envpool, dummy, subproc, ...")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--save-dir", default="cgac_zoo")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as log_folder:
        # The entry of hyperparams/cgac.yml (n_envs, VecNormalize, the entropy-schedule callback, ...) and its env
        model, manager = build_model(
            "cgac", args.env, seed=args.seed, backend=args.backend, log_folder=log_folder, n_timesteps=args.timesteps
        )
    print(f"{args.env}: {type(model).__name__} with {model.n_envs} envs")
    model.learn(args.timesteps, callback=manager.callbacks, log_interval=100)

    save_dir = Path(args.save_dir)
    save_dir.mkdir(parents=True, exist_ok=True)
    model.save(save_dir / "model")
    vec_normalize = model.get_vec_normalize_env()
    if vec_normalize is not None:  # the observation statistics are part of the policy: keep them with it
        vec_normalize.save(str(save_dir / "vecnormalize.pkl"))
    print(f"Saved to {save_dir}/")


if __name__ == "__main__":
    main()
