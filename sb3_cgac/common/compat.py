"""
Models saved by earlier releases. A file of 0.1.0 loads when it used none of the options that 0.2.0 removed, and fails
with a message that names the release to load it with otherwise. Files of 0.1.0 and 0.2.0 did not record the policy's
defaults: they build their policy with those releases' defaults, whatever this release's are. Later files record the
defaults they were saved with.
"""

import inspect
from typing import Any

import torch as th

# The 0.1.0 release: a git tag of this repository (and its version.txt)
PREVIOUS_RELEASE = "sb3_cgac 0.1.0 (git tag v0.1.0, commit dd52c51)"

# Constructor arguments that 0.1.0 had and this release removed, with their 0.1.0 defaults: a saved model that kept
# the default trains here as it did there
REMOVED_ARGUMENTS: dict[str, Any] = {
    "critic_learning_rate": None,
    "ent_coef_learning_rate": None,
    "final_learning_rate": None,
    "lr_decay_iterations": None,  # meaningless without final_learning_rate
    "decay_ent_coef_learning_rate": False,
    "refresh_target_values": False,
    "entropy_schedule": None,
    "entropy_schedule_kwargs": {},
    "actor_max_grad_norm": None,
    "clip_actor_gradient_outliers": False,
    "behaviour_kl_coef": 0.0,
    "compile_updates": False,
}
# Derived state that 0.1.0 saved and this release rebuilds (the resolved values are the public attributes now)
DERIVED_ATTRIBUTES = (
    "critic_lr_schedule",
    "ent_coef_lr_schedule",
    "_batch_size",
    "_critic_updates_per_step",
    "_tau",
    "_policy_tau",
)
# Policy keyword arguments that 0.1.0 had and this release removed, with their 0.1.0 defaults
REMOVED_POLICY_KWARGS: dict[str, Any] = {
    "state_dependent_std": False,
    "stack_critics": False,
    "critic_float32_output": True,
}
# The defaults of CGACPolicy's keyword arguments in 0.1.0 and 0.2.0 (the same in both; net_arch None meant these sizes)
POLICY_DEFAULTS_0_2: dict[str, Any] = {
    "net_arch": [256, 256],
    "log_std_init": -1.0,
    "use_xavier_init": True,
    "mean_init_scale": 1.0,
    "normalize_images": True,
    "n_critics": 2,
    "share_features_extractor": False,
    "normalize_observations": False,
    "critic_layer_norm": False,
    "n_bins": None,
    "actor_q_reduction": "min",
}
# What replaced an option, for the error message
REPLACEMENTS = {
    "final_learning_rate": "learning_rate=stable_baselines3.common.utils.LinearSchedule(start, end, end_fraction)",
    "entropy_schedule": "callback=sb3_cgac.callbacks.RewardEntropySchedule(...) or ProgressEntropySchedule(...) in learn()",
}


def upgrade_saved_attributes(attributes: dict[str, Any]) -> None:
    """
    Remove, in place, the attributes of a model loaded from an sb3_cgac 0.1.0 file that this release no longer has,
    when they hold their 0.1.0 defaults; raise a ValueError that names the release to use when one does not.

    :param attributes: The model's ``__dict__`` after SB3's ``load`` updated it with the saved data
    """
    if "behaviour_kl_coef" not in attributes:
        return  # saved by this release (or a newer one)
    used = []
    for name, default in REMOVED_ARGUMENTS.items():
        value = attributes.pop(name, default)
        if name != "lr_decay_iterations" and value != default:
            used.append(f"{name}={value!r}")
    for name in DERIVED_ATTRIBUTES:
        attributes.pop(name, None)
    policy_kwargs = dict(attributes.get("policy_kwargs") or {})
    for name, default in REMOVED_POLICY_KWARGS.items():
        value = policy_kwargs.pop(name, default)
        if value != default:
            used.append(f"policy_kwargs {name}={value!r}")
    if used:
        hints = [f"{name}: {hint}" for name, hint in REPLACEMENTS.items() if any(item.startswith(name) for item in used)]
        raise ValueError(
            f"CGAC: this model was saved by sb3_cgac 0.1.0 with {', '.join(used)}, which this release removed. Load it "
            f"with {PREVIOUS_RELEASE}: in a checkout of this repository, git checkout v0.1.0 && pip install -e ."
            + (f" To train anew here, {'; '.join(hints)}." if hints else "")
        )
    attributes["policy_kwargs"] = policy_kwargs
    # 0.1.0 saved the running average of its actor-gradient outlier clipping with the model: SB3's loader sets it
    # after this call, so it needs an attribute to write into (unused here, and not saved again)
    attributes.setdefault("gradient_ratio_average", th.zeros(()))


def policy_defaults(policy_class: type) -> dict[str, Any]:
    """
    :param policy_class: The model's policy class
    :return: The defaults of its keyword arguments that are plain values (numbers, strings, booleans, None, lists):
        saved with a model, so that it builds the same policy when a later release changes a default
    """
    plain = (type(None), bool, int, float, str, list)
    defaults: dict[str, Any] = {}
    for klass in policy_class.__mro__:  # a subclass's own defaults, then those of the classes its **kwargs reach
        if "__init__" not in vars(klass):
            continue
        parameters = inspect.signature(vars(klass)["__init__"]).parameters.values()
        for p in parameters:
            if p.default is not p.empty and isinstance(p.default, plain):
                defaults.setdefault(p.name, p.default)
        if all(p.kind != p.VAR_KEYWORD for p in parameters):
            break
    return defaults


def upgrade_saved_defaults(attributes: dict[str, Any], policy_class: type) -> dict[str, Any]:
    """
    The policy defaults that a model builds its policy with: those saved with it, those of 0.1.0 and 0.2.0 for a file of
    theirs (which saved none), or the policy class's own for a new model. A file of 0.1.0 or 0.2.0 also gets
    ``scale_rewards`` from what it saved (0.1.0 had no such option).

    :param attributes: The model's ``__dict__``: after SB3's ``load`` updated it with the saved data, or new
    :param policy_class: The model's policy class
    :return: The defaults, to save with the model
    """
    if "policy_defaults" in attributes:
        return attributes["policy_defaults"]  # saved by this release or a later one
    if "batch_size" not in attributes:
        return policy_defaults(policy_class)  # a new model: resolved batch sizes are saved, a constructor sets none
    attributes["scale_rewards"] = attributes.get("return_scale") is not None  # their running statistics, if any
    accepted = policy_defaults(policy_class)
    return {name: value for name, value in POLICY_DEFAULTS_0_2.items() if name in accepted}
