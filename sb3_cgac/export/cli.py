"""The command line of ``python -m sb3_cgac.export`` (the package's docstring documents it)."""

import argparse
import pickle
from pathlib import Path
from typing import NoReturn

from stable_baselines3.common.vec_env import VecNormalize

from sb3_cgac.export.actor import EXPORT_FORMATS, export_policy

DESCRIPTION = (
    "Export the deterministic actor of a trained CGAC model for deployment, as ONNX (extra export: onnx, onnxruntime), "
    "a torch.export program (.pt2: torch.export.load(path).module() runs it, without this package) or TorchScript "
    "(kept for the robot stacks that load it, such as Isaac Lab's and rsl_rl's exported policies; torch 2.10 "
    "deprecated torch.jit.trace, and pt2 is its successor), with observation normalisation (VecNormalize statistics "
    "and the policy's own) and the scaling of actions to the action space's bounds baked in: the exported module maps "
    "raw observations to the actions that model.predict(obs, deterministic=True) returns."
)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m sb3_cgac.export", description=DESCRIPTION)
    parser.add_argument("model", help="a saved CGAC model (.zip)")
    parser.add_argument(
        "--output", required=True, help="the file to write (.onnx: ONNX, .pt2: torch.export, else TorchScript)"
    )
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
        try:
            with open(args.vec_normalize, "rb") as file_handler:
                vec_normalize = pickle.load(file_handler)
        except Exception as error:
            fail(f"{args.vec_normalize} does not load as VecNormalize statistics ({type(error).__name__}: {error})")
        if not isinstance(vec_normalize, VecNormalize):
            fail(f"{args.vec_normalize} holds a {type(vec_normalize).__name__}, not VecNormalize statistics")
    path = export_policy(model, args.output, vec_normalize=vec_normalize, export_format=args.format)
    print(f"Wrote the deterministic actor of {args.model} to {path}")
