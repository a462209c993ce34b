"""
The exported actor (ONNX through onnxruntime, torch.export's .pt2, TorchScript) gives the actions of
predict(deterministic=True).
"""

import pickle
import warnings

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize
from toy_envs import DictObsEnv  # tests/ is on sys.path under pytest

from sb3_cgac import CGAC
from sb3_cgac.export import export_policy, main

ort = pytest.importorskip("onnxruntime")

N_OBS = 1000


def trained(policy: str, env: VecNormalize, **kwargs) -> CGAC:
    model = CGAC(policy, env, policy_kwargs=dict(net_arch=[32, 32], **kwargs.pop("policy_kwargs", {})), seed=0, **kwargs)
    model.learn(env.num_envs * 60)  # updates from the 32nd step on: the networks and the statistics move
    return model


def raw_observations(env: VecNormalize) -> np.ndarray | dict[str, np.ndarray]:
    # Observations as the env emits them, before VecNormalize, spread beyond the statistics' range
    rng = np.random.default_rng(0)
    space = env.observation_space
    if hasattr(space, "spaces"):
        return {key: rng.normal(0, 3, (N_OBS, *sub.shape)).astype(np.float32) for key, sub in space.spaces.items()}
    return rng.normal(0, 3, (N_OBS, *space.shape)).astype(np.float32)


def onnx_actions(path, obs) -> np.ndarray:
    session = ort.InferenceSession(str(path))
    feeds = obs if isinstance(obs, dict) else {"obs": obs}
    return session.run(None, feeds)[0]


@pytest.mark.parametrize("predict_tau", [None, 0.05])
def test_onnx_matches_predict_box(tmp_path, predict_tau):
    """Pendulum-v1 with VecNormalize and the policy's own normaliser: both are in the exported graph."""
    env = VecNormalize(make_vec_env("Pendulum-v1", n_envs=8, seed=0), norm_reward=False)
    model = trained("MlpPolicy", env, predict_tau=predict_tau, policy_kwargs=dict(normalize_observations=True))
    obs = raw_observations(env)
    expected, _ = model.predict(env.normalize_obs(obs), deterministic=True)
    path = export_policy(model, tmp_path / "policy.onnx", vec_normalize=env)
    actions = onnx_actions(path, obs)
    assert actions.shape == (N_OBS, 1)
    np.testing.assert_allclose(actions, expected, atol=1e-5, rtol=0)
    assert np.abs(expected).max() > 0.1, "the check needs actions away from zero"
    # torch.export's program and TorchScript give the same
    program = th.export.load(str(export_policy(model, tmp_path / "policy.pt2", vec_normalize=env))).module()
    np.testing.assert_allclose(program(th.as_tensor(obs)).numpy(), expected, atol=1e-5, rtol=0)
    scripted = th.jit.load(str(export_policy(model, tmp_path / "policy.pt", vec_normalize=env)))
    np.testing.assert_allclose(scripted(th.as_tensor(obs)).numpy(), expected, atol=1e-5, rtol=0)


@pytest.mark.parametrize("suffix", [".onnx", ".pt2", ".pt"])
def test_export_prints_no_deprecation_warning(tmp_path, suffix):
    model = trained("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=8, seed=0))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        export_policy(model, tmp_path / f"policy{suffix}")
    deprecations = [str(item.message) for item in caught if issubclass(item.category, DeprecationWarning | FutureWarning)]
    assert not deprecations, deprecations


def test_pt2_matches_predict_dict(tmp_path):
    env = VecNormalize(make_vec_env(DictObsEnv, n_envs=8, seed=0), norm_reward=False)
    model = trained("MultiInputPolicy", env, policy_kwargs=dict(normalize_observations=True))
    obs = raw_observations(env)
    expected, _ = model.predict(env.normalize_obs(obs), deterministic=True)
    program = th.export.load(str(export_policy(model, tmp_path / "policy.pt2", vec_normalize=env))).module()
    actions = program(*(th.as_tensor(obs[key]) for key in ("position", "velocity"))).numpy()
    np.testing.assert_allclose(actions, expected, atol=1e-5, rtol=0)


def test_onnx_matches_predict_dict(tmp_path):
    env = VecNormalize(make_vec_env(DictObsEnv, n_envs=8, seed=0), norm_reward=False)
    model = trained("MultiInputPolicy", env)
    obs = raw_observations(env)
    expected, _ = model.predict(env.normalize_obs(obs), deterministic=True)
    path = export_policy(model, tmp_path / "policy.onnx", vec_normalize=env)
    assert [node.name for node in ort.InferenceSession(str(path)).get_inputs()] == ["position", "velocity"]
    np.testing.assert_allclose(onnx_actions(path, obs), expected, atol=1e-5, rtol=0)
    # Without VecNormalize the exported actor takes the observations as predict() does
    plain = trained("MultiInputPolicy", make_vec_env(DictObsEnv, n_envs=8, seed=0))
    path = export_policy(plain, tmp_path / "plain.onnx")
    np.testing.assert_allclose(onnx_actions(path, obs), plain.predict(obs, deterministic=True)[0], atol=1e-5, rtol=0)


def test_export_cli(tmp_path, capsys):
    env = VecNormalize(make_vec_env("Pendulum-v1", n_envs=8, seed=0), norm_reward=False)
    model = trained("MlpPolicy", env)
    model.save(tmp_path / "model")
    env.save(str(tmp_path / "vecnormalize.pkl"))
    model_path, statistics = str(tmp_path / "model.zip"), str(tmp_path / "vecnormalize.pkl")
    main([model_path, "--output", str(tmp_path / "out.onnx"), "--vec-normalize", statistics])
    assert "Wrote the deterministic actor" in capsys.readouterr().out
    obs = raw_observations(env)
    expected, _ = model.predict(env.normalize_obs(obs), deterministic=True)
    np.testing.assert_allclose(onnx_actions(tmp_path / "out.onnx", obs), expected, atol=1e-5, rtol=0)
    main([model_path, "--output", str(tmp_path / "out.pt2"), "--vec-normalize", statistics])
    program = th.export.load(str(tmp_path / "out.pt2")).module()
    np.testing.assert_allclose(program(th.as_tensor(obs)).numpy(), expected, atol=1e-5, rtol=0)
    # Something that is not VecNormalize statistics is refused with a message
    with open(tmp_path / "other.pkl", "wb") as file_handler:
        pickle.dump({"not": "statistics"}, file_handler)
    with pytest.raises(SystemExit):
        main([model_path, "--output", str(tmp_path / "x.onnx"), "--vec-normalize", str(tmp_path / "other.pkl")])
    assert "not VecNormalize statistics" in capsys.readouterr().err


@pytest.mark.parametrize(
    "arguments, message",
    [
        (["nothere.zip", "--output", "x.onnx"], "no model file nothere.zip"),
        (["{model}", "--output", "x.onnx", "--vec-normalize", "nothere.pkl"], "no VecNormalize file nothere.pkl"),
        (["{not_a_model}", "--output", "x.onnx"], "does not load as a CGAC model"),
    ],
)
def test_export_cli_bad_input_in_one_line(tmp_path, capsys, arguments, message):
    model = CGAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=2, seed=0), policy_kwargs=dict(net_arch=[8]), seed=0)
    model.save(tmp_path / "model")
    (tmp_path / "not_a_model.zip").write_text("not a zip")
    names = dict(model=str(tmp_path / "model.zip"), not_a_model=str(tmp_path / "not_a_model.zip"))
    with pytest.raises(SystemExit) as stop:
        main([argument.format(**names) for argument in arguments])
    assert stop.value.code == 2
    error = capsys.readouterr().err
    # One line of ours, last (a dependency may print its own notices on import), and no stack trace
    assert message in error.strip().splitlines()[-1] and "Traceback" not in error, error
