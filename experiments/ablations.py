"""
The paper's ablations (Fig. 3) on a cheap env: number of parallel envs, no policy averaging, no value averaging,
neither, no alpha clamp and the paper's alpha clamp; and this package's stabilisers switched on one at a time:
first episodes cut at random lengths, the learning-rate decay (to 1e-4 over a quarter of the entry's n_timesteps),
AdamW's weight decay (``weight_decay``), the authors' larger critics (``big_critic``: [512, 512, 256]), no observation
normalisation (``no_obs_norm``) or normalisation inside the policy instead of ``VecNormalize`` (``policy_obs_norm``),
and the actor's initial mean layer scaled by 0.01 (``small_mean_init``) or not (``full_mean_init``).
Each variant is the ``cgac`` entry of ``hyperparams/cgac.yml`` (or of ``--conf-dir``'s) with one change, run by
``sb3_cgac.compare`` (same budget options, CSV, plots and table; times are compared with the full CGAC)::

    python experiments/ablations.py --env HalfCheetah-v5 --backend envpool --seeds 2 --minutes 10 --jobs 2
    python experiments/ablations.py --env Hopper-v5 --steps 2000000 --variants cgac no_pol_avg no_val_avg

``--n-envs`` sets the env counts of the parallel-env variants (default: a quarter and four times the entry's).
"""

import argparse
from pathlib import Path
from typing import Any

import torch as th
import yaml

from sb3_cgac.compare import main as compare_main
from sb3_cgac.policies import DEFAULT_NET_ARCH
from sb3_cgac.zoo import HYPERPARAMS_DIR


class _Code(str):
    """A Python expression (a class, say) that goes into a ``policy_kwargs`` string as code, not as a quoted string."""

    def __repr__(self) -> str:
        return str(self)


ADAMW = _Code("th.optim.AdamW")  # the zoo evaluates policy_kwargs with torch imported as th

VARIANTS: dict[str, dict[str, Any]] = {
    "cgac": {},
    "no_pol_avg": {"policy_tau": 1.0},  # the averaged actor is the actor
    "no_val_avg": {"tau": 1.0},  # the target critic is the critic
    "no_polval_avg": {"policy_tau": 1.0, "tau": 1.0},
    "no_alpha_clamp": {"ent_coef_monotone": False},
    "paper_alpha_clamp": {"ent_coef_monotone": True},  # alpha never increases, even below the target entropy
    "random_first_episode": {"random_first_episode": True},
    # The authors' linear decay, over a quarter of the entry's n_timesteps
    "lr_decay": {"learning_rate": "lin_2e-3_1e-4_0.25"},
    # Decoupled weight decay at AdamW's default coefficient (SimBa's; FastTD3 uses 0.1 with a smaller learning rate)
    "weight_decay": {"policy_kwargs": {"optimizer_class": ADAMW, "optimizer_kwargs": {"weight_decay": 0.01}}},
    # The authors' default critic width (their README commands use [1024, 1024, 256]); the actor keeps the entry's
    "big_critic": {"policy_kwargs": {"net_arch": {"qf": [512, 512, 256]}}},
    "no_obs_norm": {"normalize": False},
    # Running mean/std inside the policy (saved with it), clipped at 5 as the authors do, instead of VecNormalize
    "policy_obs_norm": {"normalize": False, "policy_kwargs": {"normalize_observations": True}},
    # The actor's initial mean layer scaled by 0.01 (near-zero initial actions), or left as initialised (the paper's)
    "small_mean_init": {"policy_kwargs": {"mean_init_scale": 0.01}},
    "full_mean_init": {"policy_kwargs": {"mean_init_scale": 1.0}},
}


def entry_variants(entry: dict[str, Any], n_envs: list[int] | None = None) -> dict[str, dict[str, Any]]:
    """
    The overrides of each variant for one YAML entry.

    :param entry: The ``cgac`` entry of the env
    :param n_envs: Env counts of the ``n_envs_<N>`` variants (default: a quarter and four times the entry's)
    :return: Variant name -> hyperparameters that replace the entry's
    """
    variants = {name: dict(overrides) for name, overrides in VARIANTS.items()}
    # The actor of big_critic keeps the entry's layers: the critic alone gets wider
    critic_arch = variants["big_critic"]["policy_kwargs"]["net_arch"]
    variants["big_critic"]["policy_kwargs"] = {"net_arch": {"pi": _actor_arch(entry), **critic_arch}}
    for overrides in variants.values():
        if isinstance(overrides.get("policy_kwargs"), dict):
            # Added to (or replacing keys of) the entry's own policy_kwargs, a "dict(...)" string in the YAML file
            extra = ", ".join(f"{key!r}: {value!r}" for key, value in overrides["policy_kwargs"].items())
            overrides["policy_kwargs"] = f"{{**{entry.get('policy_kwargs', 'dict()')}, {extra}}}"
    for count in n_envs or [max(1, entry["n_envs"] // 4), entry["n_envs"] * 4]:
        variants[f"n_envs_{count}"] = {"n_envs": count}
        if (entry.get("batch_size") or 0) > count * entry.get("buffer_window", 32):
            # The entry's batch does not fit in the smaller window: CGAC's default (the whole window) instead
            variants[f"n_envs_{count}"]["batch_size"] = "auto"
    return variants


def unchanged_variants(entry: dict[str, Any], variants: dict[str, dict[str, Any]]) -> list[str]:
    """
    The variants (other than ``cgac``) whose overrides the entry already has, so that they would rerun the entry.

    :param entry: The ``cgac`` entry of the env
    :param variants: Variant name -> overrides (``entry_variants``)
    :return: Their names
    """
    # An entry without a normalize key trains without VecNormalize, as normalize: False does
    entry = {"normalize": False, **entry}
    return [
        name
        for name, overrides in variants.items()
        if overrides and all(key in entry and entry[key] == value for key, value in overrides.items())
    ]


def _actor_arch(entry: dict[str, Any]) -> list[int]:
    """The actor's hidden layers in a YAML entry (the policy's default where it names none)."""
    policy_kwargs = entry.get("policy_kwargs") or {}
    if isinstance(policy_kwargs, str):
        # The zoo evaluates this string with torch as ``th`` in scope; so does this
        policy_kwargs = eval(policy_kwargs, {"th": th, "nn": th.nn})
    net_arch = policy_kwargs.get("net_arch")
    if net_arch is None:
        return list(DEFAULT_NET_ARCH)
    return list(net_arch["pi"] if isinstance(net_arch, dict) else net_arch)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python experiments/ablations.py",
        description=__doc__,
        epilog="Every other option is the comparison's (python -m sb3_cgac.compare --help): the budget (--steps or "
        "--minutes), --seeds, the evaluation options, --threshold, --backend, --jobs, --threads, --summary-only.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        allow_abbrev=False,  # the comparison's options pass through unabbreviated
    )
    parser.add_argument("--env", required=True, help="env id; its cgac entry is the one varied")
    parser.add_argument("--variants", nargs="+", default=None, help=f"subset of {list(VARIANTS)} and n_envs_<N>")
    parser.add_argument("--n-envs", nargs="+", type=int, default=None, help="env counts of the n_envs variants")
    parser.add_argument("--conf-dir", default=None, help="folder of cgac.yml (default: this package's hyperparams)")
    parser.add_argument("--out", default=None, help="output folder (default: results/ablations-<env>)")
    return parser


def load_entry(env_id: str, conf_dir: str | None = None) -> dict[str, Any]:
    """
    The ``cgac`` entry the variants change: the one the runs read (``--conf-dir``'s file, else the package's).

    :param env_id: Env id
    :param conf_dir: Folder of ``cgac.yml`` (None: this package's hyperparameters)
    :return: The entry
    """
    path = Path(conf_dir or HYPERPARAMS_DIR) / "cgac.yml"
    if not path.is_file():
        raise ValueError(f"{path} does not exist: --conf-dir must be a folder holding cgac.yml.")
    entries = yaml.safe_load(path.read_text()) or {}
    if env_id not in entries:
        raise ValueError(
            f"{path} has no entry for {env_id}: the ablations vary an entry. Add one, or pick one of {sorted(entries)}."
        )
    return entries[env_id]


def main(argv: list[str] | None = None) -> None:
    parser = build_parser()
    known, rest = parser.parse_known_args(argv)
    if any(arg == "--runs" or arg.startswith("--runs=") for arg in rest):
        parser.error("--runs does not apply to the ablations: choose them with --variants")
    try:
        entry = load_entry(known.env, known.conf_dir)
    except ValueError as error:
        parser.error(str(error))
    variants = entry_variants(entry, known.n_envs)
    chosen = known.variants or list(variants)
    unknown = [name for name in chosen if name not in variants]
    if unknown:
        parser.error(f"unknown variants {unknown}; choose from {list(variants)}")
    unchanged = unchanged_variants(entry, variants)
    same = [name for name in chosen if name in unchanged]
    if same and known.variants:
        parser.error(
            f"variants {same} change nothing in the {known.env} entry (it already has {[variants[n] for n in same]}): "
            "drop them, or pass --conf-dir with the entry they should change"
        )
    if same:
        print(f"Leaving out {same}: the {known.env} entry already has their settings.")
        chosen = [name for name in chosen if name not in same]
    runs = {name: {"file": "cgac", "overrides": variants[name]} for name in chosen}
    rest += ["--env", known.env, "--out", known.out or str(Path("results") / f"ablations-{known.env}")]
    rest += ["--conf-dir", known.conf_dir] if known.conf_dir else []
    compare_main(runs=runs, argv=rest, references=("cgac",))


if __name__ == "__main__":
    main()
