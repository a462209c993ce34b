"""
The deterministic actor of a CGAC model as a standalone module (normalisation and action scaling inside), written
as ONNX, a ``torch.export`` program (``.pt2``) or TorchScript.
"""

import copy
import importlib.util
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecNormalize
from torch import nn

EXPORT_FORMATS = ("onnx", "pt2", "torchscript")
# The format of a file suffix (any other suffix: TorchScript)
SUFFIX_FORMATS = {".onnx": "onnx", ".pt2": "pt2"}


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
    Write the deterministic actor of ``model`` (see :class:`DeterministicActor`) to ``path``, with a dynamic batch
    dimension: ONNX from torch's current exporter (``torch.onnx.export(..., dynamo=True)``, which needs ``onnxscript``:
    extra ``export``); ``pt2``, a ``torch.export`` program (``torch.export.load(path).module()`` runs it, without this
    package); TorchScript (``torch.jit.load``), for the robot stacks that load it (Isaac Lab's, rsl_rl's exported
    policies), traced under a filter of the deprecation warning of ``torch.jit.trace`` in torch >= 2.10.

    :param model: A trained ``CGAC`` model
    :param path: Output file (``.onnx``: ONNX, ``.pt2``: torch.export, else TorchScript unless ``export_format`` says)
    :param vec_normalize: The ``VecNormalize`` the model was trained with, if any (its observation statistics)
    :param export_format: ``"onnx"``, ``"pt2"`` or ``"torchscript"`` (default: from the file's suffix)
    :param opset_version: ONNX opset (at least 18, the exporter's)
    :return: The path written
    """
    path = Path(path)
    export_format = export_format or SUFFIX_FORMATS.get(path.suffix, "torchscript")
    if export_format not in EXPORT_FORMATS:
        raise ValueError(f"Unknown export format {export_format!r}; choose one of {EXPORT_FORMATS}.")
    module = DeterministicActor(model, vec_normalize).eval()
    if export_format == "torchscript":
        with warnings.catch_warnings():
            # TorchScript stays for the deployment stacks that load it; torch.export (format "pt2") is its successor
            warnings.filterwarnings("ignore", message=r"`torch\.jit\.trace", category=DeprecationWarning)
            th.jit.trace(module, module.example_inputs()).save(str(path))
        return path
    # A batch of 2 in the example: torch.export specialises a dimension of size 1 to a constant
    inputs = module.example_inputs(batch_size=2)
    batch = th.export.Dim("batch")
    names = module.input_names()
    # forward(*observations): one structure holding a shape per observation
    dynamic_shapes = (tuple({0: batch} for _ in names),)
    if export_format == "onnx" and importlib.util.find_spec("onnxscript") is None:
        raise ImportError("ONNX export needs onnxscript (torch's ONNX exporter uses it): pip install 'sb3_cgac[export]'.")
    with warnings.catch_warnings():
        # torch.export's own use of a pytree API that torch 2.13 deprecated: nothing a user of this function can change
        warnings.filterwarnings("ignore", message=r"`isinstance\(treespec, LeafSpec\)` is deprecated", category=FutureWarning)
        if export_format == "pt2":
            th.export.save(th.export.export(module, inputs, dynamic_shapes=dynamic_shapes), str(path))
        else:
            _export_onnx(module, inputs, path, names, dynamic_shapes, opset_version)
    return path


def _export_onnx(
    module: DeterministicActor, inputs: tuple[th.Tensor, ...], path: Path, names: list[str], dynamic_shapes: Any, opset: int
) -> None:
    th.onnx.export(
        module,
        inputs,
        str(path),
        input_names=names,
        output_names=["actions"],
        dynamic_shapes=dynamic_shapes,
        opset_version=opset,
        dynamo=True,
        external_data=False,
        verbose=False,
    )
