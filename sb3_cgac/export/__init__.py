"""
Export the deterministic actor of a trained CGAC model for deployment, as ONNX (extra ``export``: onnx, onnxruntime),
a ``torch.export`` program (``.pt2``) or TorchScript: observation normalisation (``VecNormalize`` statistics and the
policy's own) and the scaling of actions to the action space's bounds are baked in, so that the exported module maps
raw observations to the actions that ``model.predict(obs, deterministic=True)`` returns::

    python -m sb3_cgac.export logs/cgac/Go1JoystickFlatTerrain-v1_1/best_model.zip --output go1.onnx \\
        --vec-normalize logs/cgac/Go1JoystickFlatTerrain-v1_1/Go1JoystickFlatTerrain-v1/vecnormalize.pkl

From Python: ``export_policy(model, "policy.onnx", vec_normalize=env)``. A Box observation is one input, ``obs``; a
Dict observation is one input per key the actor reads (the policy's ``actor_keys``, else every key), named by the keys,
in the order of the observation space.

The package: ``actor`` builds the exported module and writes the file (``export_policy``); ``cli`` is the command line.
"""

from sb3_cgac.export.actor import EXPORT_FORMATS, DeterministicActor, export_policy
from sb3_cgac.export.cli import main

__all__ = ["EXPORT_FORMATS", "DeterministicActor", "export_policy", "main"]
