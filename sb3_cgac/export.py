"""
Export the deterministic actor of a trained CGAC model for deployment, as ONNX (extra ``export``: onnx, onnxruntime)
or TorchScript: observation normalisation (``VecNormalize`` statistics and the policy's own) and the scaling of
actions to the action space's bounds are baked in, so that the exported module maps raw observations to the actions
that ``model.predict(obs, deterministic=True)`` returns::

    python -m sb3_cgac.export logs/cgac/Go1JoystickFlatTerrain-v1_1/best_model.zip --output go1.onnx \\
        --vec-normalize logs/cgac/Go1JoystickFlatTerrain-v1_1/Go1JoystickFlatTerrain-v1/vecnormalize.pkl

From Python: ``export_policy(model, "policy.onnx", vec_normalize=env)``. A Box observation is one input, ``obs``; a
Dict observation is one input per key the actor reads (the policy's ``actor_keys``, else every key), named by the keys,
in the order of the observation space.
"""

import argparse
import copy
import importlib.util
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecNormalize
from torch import nn

EXPORT_FORMATS = ("onnx", "torchscript")


class DeterministicActor(nn.Module):
    """
    The actor that ``predict()`` acts with (the averaged actor, or the ``predict_tau`` average), on the CPU, as a
    plain module: raw observations in, deterministic actions in the action space's bounds out.

    :param model: A trained ``CGAC`` model
    :param vec_normalize: The ``VecNormalize`` wrapper (or its loaded statistics) the model was trained with, if any
    """

    low: th.Tensor
    high: th.Tensor

    def __init__(self, model: Any, vec_normalize: VecNormalize | None = None):
        super().__init__()
        policy = model.policy
        actor = policy.actor_predict if policy.actor_predict is not None else policy.actor_avg
        self.actor = copy.deepcopy(actor).cpu().eval().requires_grad_(False)
        space = policy.observation_space
        # A Dict observation's inputs: the keys the actor reads (actor_keys), in the observation space's order
        actor_keys = (policy.actor_keys or list(space.spaces)) if isinstance(space, spaces.Dict) else None
        self.keys: list[str] | None = None if actor_keys is None else [key for key in space.spaces if key in actor_keys]
        action_space = policy.action_space
        self.register_buffer("low", th.as_tensor(action_space.low, dtype=th.float32))
        self.register_buffer("high", th.as_tensor(action_space.high, dtype=th.float32))
        # VecNormalize's observation statistics, per key for a Dict space (only the keys it normalises)
        self.normalized: list[str] = []
        self.clip_obs, self.epsilon = 0.0, 0.0
        if vec_normalize is not None and vec_normalize.norm_obs:
            self.clip_obs, self.epsilon = float(vec_normalize.clip_obs), float(vec_normalize.epsilon)
            statistics: Any = vec_normalize.obs_rms
            if self.keys is None:
                statistics = {"obs": statistics}
                self.normalized = ["obs"]
            else:
                self.normalized = [key for key in vec_normalize.norm_obs_keys or [] if key in self.keys]  # type: ignore[operator]
            for key in self.normalized:
                rms = statistics[key]
                self.register_buffer(f"mean_{key}", th.as_tensor(rms.mean, dtype=th.float32))
                self.register_buffer(f"std_{key}", th.as_tensor(np.sqrt(rms.var + self.epsilon), dtype=th.float32))

    def _normalize(self, key: str, obs: th.Tensor) -> th.Tensor:
        obs = obs.float()
        if key not in self.normalized:
            return obs
        mean, std = getattr(self, f"mean_{key}"), getattr(self, f"std_{key}")
        return ((obs - mean) / std).clamp(-self.clip_obs, self.clip_obs)

    def forward(self, *observations: th.Tensor) -> th.Tensor:
        """
        :param observations: One batch of observations (Box), or one batch per key of a Dict space, in its order
        :return: The deterministic actions, shape (batch, action_dim), in the action space's bounds
        """
        obs: th.Tensor | dict[str, th.Tensor]
        if self.keys is None:
            obs = self._normalize("obs", observations[0])
        else:
            obs = {key: self._normalize(key, value) for key, value in zip(self.keys, observations, strict=True)}
        mean_actions, _ = self.actor.get_action_dist_params(obs)
        # The squashed Gaussian's deterministic action, then predict()'s unscaling to the bounds
        return self.low + 0.5 * (th.tanh(mean_actions) + 1.0) * (self.high - self.low)

    def input_names(self) -> list[str]:
        return ["obs"] if self.keys is None else list(self.keys)

    def example_inputs(self, batch_size: int = 1) -> tuple[th.Tensor, ...]:
        space = self.actor.observation_space
        spaces_ = [space] if self.keys is None else [space[key] for key in self.keys]  # type: ignore[index]
        return tuple(th.zeros((batch_size, *sub.shape), dtype=th.float32) for sub in spaces_)


def export_policy(
    model: Any,
    path: str | Path,
    vec_normalize: VecNormalize | None = None,
    export_format: str | None = None,
    opset_version: int = 18,
) -> Path:
    """
    Write the deterministic actor of ``model`` (see :class:`DeterministicActor`) to ``path``. ONNX files come from
    torch's current exporter (``torch.onnx.export(..., dynamo=True)``, which needs ``onnxscript``: extra ``export``),
    with a dynamic batch dimension.

    :param model: A trained ``CGAC`` model
    :param path: Output file (``.onnx`` for ONNX, ``.pt`` for TorchScript unless ``export_format`` says)
    :param vec_normalize: The ``VecNormalize`` the model was trained with, if any (its observation statistics)
    :param export_format: ``"onnx"`` or ``"torchscript"`` (default: from the file's suffix, ONNX for ``.onnx``)
    :param opset_version: ONNX opset (at least 18, the exporter's)
    :return: The path written
    """
    path = Path(path)
    export_format = export_format or ("onnx" if path.suffix == ".onnx" else "torchscript")
    if export_format not in EXPORT_FORMATS:
        raise ValueError(f"Unknown export format {export_format!r}; choose one of {EXPORT_FORMATS}.")
    module = DeterministicActor(model, vec_normalize).eval()
    if export_format == "torchscript":
        th.jit.trace(module, module.example_inputs()).save(str(path))
        return path
    if importlib.util.find_spec("onnxscript") is None:
        raise ImportError("ONNX export needs onnxscript (torch's ONNX exporter uses it): pip install 'sb3_cgac[export]'.")
    # A batch of 2 in the example: torch.export specialises a dimension of size 1 to a constant
    inputs = module.example_inputs(batch_size=2)
    batch = th.export.Dim("batch")
    names = module.input_names()
    th.onnx.export(
        module,
        inputs,
        str(path),
        input_names=names,
        output_names=["actions"],
        # forward(*observations): one structure holding a shape per observation
        dynamic_shapes=(tuple({0: batch} for _ in names),),
        opset_version=opset_version,
        dynamo=True,
        external_data=False,
        verbose=False,
    )
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m sb3_cgac.export", description=__doc__.split("::")[0].strip())
    parser.add_argument("model", help="a saved CGAC model (.zip)")
    parser.add_argument("--output", required=True, help="the file to write (.onnx: ONNX, else TorchScript)")
    parser.add_argument("--vec-normalize", help="the VecNormalize statistics the model was trained with (.pkl)")
    parser.add_argument("--format", choices=EXPORT_FORMATS, help="default: from the output's suffix")
    args = parser.parse_args(argv)

    def fail(message: str) -> NoReturn:
        parser.exit(2, f"{parser.prog}: error: {message}\n")

    # SB3's load() adds ".zip" to a path without it
    model_path = Path(args.model)
    if not model_path.is_file() and not model_path.with_name(model_path.name + ".zip").is_file():
        fail(f"no model file {args.model}: give the .zip that model.save() wrote")
    if args.vec_normalize and not Path(args.vec_normalize).is_file():
        fail(f"no VecNormalize file {args.vec_normalize}: give the .pkl that VecNormalize.save() wrote, or leave it out")

    from sb3_cgac import CGAC

    try:
        model = CGAC.load(args.model, device="cpu")
    except Exception as error:  # a file that is not a saved CGAC model: one line, not the loader's stack
        fail(f"{args.model} does not load as a CGAC model ({type(error).__name__}: {error})")
    vec_normalize = None
    if args.vec_normalize:
        import pickle

        try:
            with open(args.vec_normalize, "rb") as file_handler:
                vec_normalize = pickle.load(file_handler)
        except Exception as error:
            fail(f"{args.vec_normalize} does not load as VecNormalize statistics ({type(error).__name__}: {error})")
        if not isinstance(vec_normalize, VecNormalize):
            fail(f"{args.vec_normalize} holds a {type(vec_normalize).__name__}, not VecNormalize statistics")
    path = export_policy(model, args.output, vec_normalize=vec_normalize, export_format=args.format)
    print(f"Wrote the deterministic actor of {args.model} to {path}")


if __name__ == "__main__":
    main()
