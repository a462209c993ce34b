"""The asymmetric actor-critic: the actor reads some keys of a Dict observation, the critics others (privileged)."""

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize
from toy_envs import PrivilegedEnv  # tests/ is on sys.path under pytest

from sb3_cgac import CGAC
from sb3_cgac.export import export_policy

ASYMMETRIC = dict(actor_keys=["state"], critic_keys=["state", "privileged_state"])


def asymmetric_model(**policy_kwargs) -> CGAC:
    env = make_vec_env(PrivilegedEnv, n_envs=8, seed=0)
    model = CGAC("MultiInputPolicy", env, policy_kwargs=dict(net_arch=[16, 16], **ASYMMETRIC, **policy_kwargs), seed=0)
    model.learn(8 * 40)
    return model


def observations(n: int = 32) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {
        "state": rng.normal(size=(n, 2)).astype(np.float32),
        "privileged_state": rng.normal(size=(n, 3)).astype(np.float32),
    }


def test_actor_reads_only_its_keys_and_critics_all():
    model = asymmetric_model()
    obs = observations()
    changed = {**obs, "privileged_state": obs["privileged_state"] + 5.0}
    # The actor (predict) ignores the privileged state, the critics do not
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], model.predict(changed, deterministic=True)[0])
    tensors = [model.policy.obs_to_tensor(o)[0] for o in (obs, changed)]
    actions = th.zeros(32, 2)
    with th.no_grad():
        q_values = [model.critic.q_values(t, actions) for t in tensors]
    assert not th.allclose(q_values[0], q_values[1])
    # predict() needs only the actor's keys, and says which are missing
    only_state = {"state": obs["state"]}
    np.testing.assert_array_equal(model.predict(only_state, deterministic=True)[0], model.predict(obs, deterministic=True)[0])
    with pytest.raises(ValueError, match=r"lacks the actor's keys \['state'\]"):
        model.predict({"privileged_state": obs["privileged_state"]})
    # The actor's first layer sees 2 inputs, the critics' 3 + 2 + 2 actions
    assert model.actor.latent_pi[0].in_features == 2
    assert model.critic.q_networks[0][0].in_features == 2 + 3 + 2


def test_save_load_and_per_key_normalisation(tmp_path):
    model = asymmetric_model(normalize_observations=True)
    normalizers = model.policy.obs_normalizer.normalizers
    assert set(normalizers) == {"state", "privileged_state"} and all(n.count > 300 for n in normalizers.values())
    model.save(tmp_path / "model")
    loaded = CGAC.load(tmp_path / "model", env=make_vec_env(PrivilegedEnv, n_envs=8, seed=1))
    assert loaded.policy.actor_keys == ["state"] and loaded.policy.critic_keys == ["state", "privileged_state"]
    for key, normalizer in normalizers.items():
        th.testing.assert_close(loaded.policy.obs_normalizer.normalizers[key].mean, normalizer.mean)
    obs = {"state": observations()["state"]}
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])
    loaded.learn(8 * 8, reset_num_timesteps=False)


def test_onnx_export_takes_only_the_actor_keys(tmp_path):
    ort = pytest.importorskip("onnxruntime")
    env = VecNormalize(make_vec_env(PrivilegedEnv, n_envs=8, seed=0), norm_reward=False)
    model = CGAC("MultiInputPolicy", env, policy_kwargs=dict(net_arch=[16, 16], **ASYMMETRIC), seed=0)
    model.learn(8 * 40)
    path = export_policy(model, tmp_path / "actor.onnx", vec_normalize=env)
    session = ort.InferenceSession(str(path))
    assert [node.name for node in session.get_inputs()] == ["state"]
    obs = observations(1000)
    expected, _ = model.predict(env.normalize_obs(obs), deterministic=True)
    np.testing.assert_allclose(session.run(None, {"state": obs["state"]})[0], expected, atol=1e-5, rtol=0)


@pytest.mark.parametrize(
    "policy_kwargs, message",
    [
        (dict(actor_keys=["joints"]), r"actor_keys=\['joints'\] names \['joints'\]; the observation's keys are"),
        (dict(critic_keys=[]), "critic_keys=\\[\\] names no key"),
        (dict(actor_keys=["state"], share_features_extractor=True), "share_features_extractor=True needs"),
    ],
)
def test_bad_keys(policy_kwargs, message):
    with pytest.raises(ValueError, match=message):
        CGAC("MultiInputPolicy", make_vec_env(PrivilegedEnv, n_envs=2), policy_kwargs=policy_kwargs)


def test_keys_need_a_dict_space():
    with pytest.raises(ValueError, match="actor_keys needs a Dict observation space"):
        CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=2), policy_kwargs=dict(actor_keys=["state"]))
