"""The zoo's commands with CGAC: ``train`` and ``enjoy`` (``python -m sb3_cgac.train``, ``.enjoy``), bad input in one line."""

import functools
import sys
import tempfile
from pathlib import Path
from typing import NoReturn

import gymnasium as gym
import yaml

from sb3_cgac.common.distributed import init_from_env, leave, world
from sb3_cgac.vec_env import register_backend_task

# manager imports rl_zoo3 first, with the install hint where the extra is missing
from sb3_cgac.zoo.manager import (
    ADAPTER_BACKENDS,
    HYPERPARAMS_DIR,
    CGACExperimentManager,
    hyperparams_file,
    register,
    swapped_attribute,
)


def _option_value(argv: list[str], names: tuple[str, ...]) -> str | None:
    for index, arg in enumerate(argv):
        for name in names:
            if arg == name and index + 1 < len(argv):
                return argv[index + 1]
            if arg.startswith(name + "="):
                return arg.split("=", 1)[1]
    return None


def _exit_with_error(prog: str, message: str) -> NoReturn:
    """Stop a command-line tool with one line that names the problem and the fix (exit status 2, as argparse)."""
    print(f"{prog}: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def _check_train_arguments(argv: list[str]) -> None:
    """The env id and its hyperparameters, checked before rl_zoo3 would fail on them with a stack trace."""
    env_id = _option_value(argv, ("--env",))
    if env_id is None or "-h" in argv or "--help" in argv:
        return
    prog = "python -m sb3_cgac.train"
    if env_id not in gym.registry and _option_value(argv, ("--gym-packages",)) is None:
        _exit_with_error(
            prog,
            f"no env {env_id!r} in gymnasium's registry: check the id, or name the package that registers it with "
            "--gym-packages (e.g. gymnasium_robotics), or the backend that builds it with --vec-env "
            "(envpool, playground, mjlab)",
        )
    conf = _option_value(argv, ("-conf", "--conf-file"))
    if conf is not None and conf.endswith((".yml", ".yaml")):
        if not Path(conf).is_file():
            _exit_with_error(prog, f"no hyperparameter file {conf}")
        entries = yaml.safe_load(Path(conf).read_text()) or {}
        if env_id not in entries:
            _exit_with_error(prog, f"{conf} has no entry for {env_id!r}; its entries are {', '.join(map(str, entries))}")


def _without_option(argv: list[str], name: str) -> list[str]:
    result, skip = [], False
    for arg in argv:
        if skip:
            skip = False
        elif arg == name:
            skip = True
        elif not arg.startswith(name + "="):
            result.append(arg)
    return result


def _quiet_rank_argv(argv: list[str]) -> list[str]:
    """The trainer's arguments for a rank other than 0: rank 0 alone evaluates, logs and saves where asked."""
    for name in ("-f", "--log-folder", "-tb", "--tensorboard-log", "--eval-freq", "--save-freq", "--verbose"):
        argv = _without_option(argv, name)
    return [*argv, "-f", tempfile.mkdtemp(prefix="sb3_cgac_rank_"), "--eval-freq", "-1", "--save-freq", "-1", "--verbose", "0"]


def train(argv: list[str] | None = None) -> None:
    """
    Run rl_zoo3's trainer (``rl_zoo3.train.train``) with CGAC registered, this package's hyperparameter files
    as the default ``--conf-file`` for cgac, ppo and sac, and the extra ``--vec-env`` backends.

    :param argv: Command-line arguments (default: ``sys.argv[1:]``)
    """
    register()
    argv = list(sys.argv[1:] if argv is None else argv)
    rank, _ = init_from_env()  # under torchrun: data-parallel training (sb3_cgac.common.distributed)
    if rank != 0:
        argv = _quiet_rank_argv(argv)
    if "-h" in argv or "--help" in argv:
        print(
            "python -m sb3_cgac.train: rl_zoo3's trainer with CGAC registered (--algo cgac). --algo cgac, ppo and sac "
            f"read {HYPERPARAMS_DIR}/<algo>.yml unless -conf is given, and --vec-env also accepts "
            f"{', '.join(ADAPTER_BACKENDS)}. rl_zoo3's own help follows.\n"
        )
    backend = _option_value(argv, ("--vec-env",)) or "dummy"
    argv = _without_option(argv, "--vec-env")
    env_id = _option_value(argv, ("--env",))
    if env_id is not None:  # ids that only a backend builds: rl_zoo3 looks the id up before building
        register_backend_task(env_id, backend)
    if backend in ("dummy", "subproc"):
        argv += ["--vec-env", backend]
    algo = _option_value(argv, ("--algo",)) or "ppo"
    if world()[1] > 1 and algo != "cgac":
        raise ValueError(f"Under torchrun only CGAC trains data-parallel; --algo {algo} would train one model per rank.")
    conf = hyperparams_file(algo)
    if _option_value(argv, ("-conf", "--conf-file")) is None and conf is not None:
        argv += ["--conf-file", str(conf)]
    _check_train_arguments(argv)
    manager = functools.partial(CGACExperimentManager, backend=backend)
    import rl_zoo3.train

    with (
        swapped_attribute(rl_zoo3.train, "ExperimentManager", manager),
        swapped_attribute(sys, "argv", ["sb3_cgac.train", *argv]),
    ):
        rl_zoo3.train.train()
    leave()  # under torchrun: every rank ends together


def enjoy(argv: list[str] | None = None) -> None:
    """
    Run rl_zoo3's ``enjoy`` (replay a trained agent) with CGAC registered.

    :param argv: Command-line arguments (default: ``sys.argv[1:]``)
    """
    register()
    argv = list(sys.argv[1:] if argv is None else argv)
    folder = _option_value(argv, ("-f", "--folder")) or "rl-trained-agents"
    algo = _option_value(argv, ("--algo",)) or "ppo"
    if "-h" not in argv and "--help" not in argv and not (Path(folder) / algo).is_dir():
        _exit_with_error(
            "python -m sb3_cgac.enjoy", f"no folder {Path(folder) / algo}: give -f the log folder that training wrote (logs)"
        )
    import rl_zoo3.enjoy

    with swapped_attribute(sys, "argv", ["sb3_cgac.enjoy", *argv]):
        rl_zoo3.enjoy.enjoy()
