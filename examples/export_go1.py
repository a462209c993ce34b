"""
Train CGAC briefly on the Go1 joystick task (MuJoCo Playground's, as envpool's C++ port) with an asymmetric
actor-critic (the actor on the robot's ``state``, the critics also on the simulator's ``privileged_state``), export
the deterministic actor to ONNX with the observation normalisation and action scaling baked in, and replay the ONNX
policy in the env, feeding it the ``state`` alone (``pip install -e ".[envpool,export]"``).

    python examples/export_go1.py [--timesteps 20000] [--n-envs 32] [--output go1.onnx]
"""

import argparse

from sb3_cgac.threads import configure_thread_spin

configure_thread_spin()  # before anything imports torch: torch's idle threads then leave envpool's cores alone

import numpy as np  # noqa: E402
import onnxruntime as ort  # noqa: E402

from sb3_cgac import CGAC  # noqa: E402
from sb3_cgac.export import export_policy  # noqa: E402
from sb3_cgac.vec_env import make_vec_env  # noqa: E402

ENV_ID = "Go1JoystickFlatTerrain-v1"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--timesteps", type=int, default=20_000)
    parser.add_argument("--n-envs", type=int, default=32)
    parser.add_argument("--replay-steps", type=int, default=300)
    parser.add_argument("--output", default="go1.onnx")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    env = make_vec_env(ENV_ID, n_envs=args.n_envs, backend="envpool", seed=args.seed)
    # The Go1 entry of hyperparams/cgac.yml: asymmetric, and starting near the standing pose with little noise
    asymmetric = dict(actor_keys=["state"], critic_keys=["privileged_state"], normalize_observations=True)
    policy_kwargs = dict(**asymmetric, mean_init_scale=0.01, log_std_init=-2.3)
    model = CGAC("MultiInputPolicy", env, policy_kwargs=policy_kwargs, target_entropy_beta=3.0, seed=args.seed, verbose=0)
    model.learn(args.timesteps)
    path = export_policy(model, args.output)
    print(f"Trained {model.num_timesteps} steps; wrote {path}")

    # Replay: the ONNX policy takes the raw observations of the actor's keys
    session = ort.InferenceSession(str(path))
    names = [node.name for node in session.get_inputs()]
    print(f"ONNX inputs: {names}")
    replay_env = make_vec_env(ENV_ID, n_envs=1, backend="envpool", seed=args.seed + 1000, random_first_episode=False)
    obs = replay_env.reset()
    total, gap = 0.0, 0.0
    for _ in range(args.replay_steps):
        assert isinstance(obs, dict)  # Go1's Dict observation
        actions = session.run(None, {name: obs[name].astype(np.float32) for name in names})[0]
        expected, _ = model.predict({"state": obs["state"]}, deterministic=True)
        gap = max(gap, float(np.abs(actions - expected).max()))
        obs, rewards, _, _ = replay_env.step(actions)
        total += float(rewards[0])
    print(f"ONNX policy: return {total:.1f} over {args.replay_steps} steps; largest gap to predict(): {gap:.2e}")


if __name__ == "__main__":
    main()
