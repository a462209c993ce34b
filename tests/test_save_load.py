import inspect
import io
import pathlib

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_cgac import CGAC
from sb3_cgac.common.compat import policy_defaults
from sb3_cgac.policies import CGACPolicy, MultiInputPolicy

SMALL = dict(policy_kwargs=dict(net_arch=[16, 16]), seed=0)
# Models saved by sb3_cgac 0.1.0 (git tag v0.1.0): Pendulum-v1, 16 envs, [16, 16] networks, batch 64, 128 steps;
# one with the defaults of 0.1.0, one with two options that this release removed
DATA = pathlib.Path(__file__).parent / "data"


def make_env(n_envs: int = 4):
    return make_vec_env("Pendulum-v1", n_envs=n_envs, seed=0)


def state_of(model: CGAC) -> dict[str, th.Tensor]:
    params = {f"policy.{name}": value.clone() for name, value in model.policy.state_dict().items()}
    if model.log_ent_coef is not None:
        params["log_ent_coef"] = model.log_ent_coef.detach().clone()
    return params


@pytest.mark.parametrize("ent_coef", ["auto_0.1", 0.05])
def test_save_load(tmp_path: pathlib.Path, ent_coef):
    env = make_env()
    model = CGAC("MlpPolicy", env, ent_coef=ent_coef, policy_tau=0.1, **SMALL)
    model.learn(600)
    # Averaged copies differ from the trained networks, so that a mix-up would show
    assert not th.allclose(model.actor.mu.weight, model.actor_avg.mu.weight)
    critic_params = zip(model.critic.parameters(), model.critic_target.parameters(), strict=True)
    assert not all(th.allclose(param, target) for param, target in critic_params)

    obs = env.reset()
    before = state_of(model)
    action_before, _ = model.predict(obs, deterministic=True)
    model.save(tmp_path / "cgac")
    del model

    loaded = CGAC.load(tmp_path / "cgac", env=env)
    after = state_of(loaded)
    assert before.keys() == after.keys()
    for key in before:
        assert th.equal(before[key], after[key]), key
    assert any(key.startswith("policy.actor_avg.") for key in after)
    assert any(key.startswith("policy.critic_target.") for key in after)
    action_after, _ = loaded.predict(obs, deterministic=True)
    assert np.array_equal(action_before, action_after)
    # Optimizer states came back (Adam has moments after training)
    assert len(loaded.actor.optimizer.state) > 0 and len(loaded.critic.optimizer.state) > 0
    if ent_coef == "auto_0.1":
        assert loaded.ent_coef_optimizer is not None and len(loaded.ent_coef_optimizer.state) > 0
    # Training goes on
    loaded.learn(200, reset_num_timesteps=False)
    assert loaded.num_timesteps >= 800


def test_save_load_buffer_like_file_objects():
    model = CGAC("MlpPolicy", make_env(), **SMALL)
    model.learn(200)
    buffer = io.BytesIO()
    model.save(buffer)
    buffer.seek(0)
    loaded = CGAC.load(buffer, device="cpu")
    assert loaded.env is None
    obs = np.zeros((1, 3), dtype=np.float32)
    assert np.array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])


def test_optimizer_state_continues_after_load(tmp_path):
    """The optimizers are restored, not re-created: Adam's step counts go on from the saved ones."""
    env = make_env()
    model = CGAC("MlpPolicy", env, **SMALL)
    model.learn(300)
    steps = {name: _adam_steps(optimizer) for name, optimizer in _optimizers(model).items()}
    model.save(tmp_path / "mid")
    loaded = CGAC.load(tmp_path / "mid", env=env)
    assert {name: _adam_steps(optimizer) for name, optimizer in _optimizers(loaded).items()} == steps
    loaded.learn(200, reset_num_timesteps=False)  # the window refills first (32 steps) after a load
    for name, optimizer in _optimizers(loaded).items():
        assert _adam_steps(optimizer) > steps[name], name


def _optimizers(model: CGAC) -> dict[str, th.optim.Optimizer]:
    assert model.ent_coef_optimizer is not None
    return {"actor": model.actor.optimizer, "critic": model.critic.optimizer, "ent_coef": model.ent_coef_optimizer}


def _adam_steps(optimizer: th.optim.Optimizer) -> float:
    return max(float(state["step"]) for state in optimizer.state.values())


def test_set_env():
    model = CGAC("MlpPolicy", make_env(), **SMALL)
    model.learn(100)
    model.set_env(make_env())
    model.learn(100)
    with pytest.raises(AssertionError, match="number of environments"):
        model.set_env(make_env(2))


def test_policy_save_load(tmp_path):
    model = CGAC("MlpPolicy", make_env(), policy_tau=0.1, **SMALL)
    model.learn(400)
    model.policy.save(tmp_path / "policy.pkl")
    policy = CGACPolicy.load(tmp_path / "policy.pkl")
    for name, value in model.policy.state_dict().items():
        assert th.equal(value, policy.state_dict()[name]), name
    obs = np.random.default_rng(0).normal(size=(5, 3)).astype(np.float32)
    assert np.array_equal(model.policy.predict(obs, deterministic=True)[0], policy.predict(obs, deterministic=True)[0])


def test_save_load_predict_actor(tmp_path):
    """The slower average that predict() acts with (predict_tau) is saved, loaded and averaged on after a load."""
    env = make_env()
    model = CGAC("MlpPolicy", env, predict_tau=0.01, **SMALL)
    model.learn(400)
    model.save(tmp_path / "slow")
    loaded = CGAC.load(tmp_path / "slow", env=env)
    assert loaded.predict_tau == 0.01 and loaded.policy.actor_predict is not None
    for name, value in state_of(model).items():
        assert th.equal(value, state_of(loaded)[name]), name
    obs = env.reset()
    assert np.array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])
    before = [param.clone() for param in loaded.policy.actor_predict.parameters()]
    updates = loaded._n_updates
    loaded.learn(400, reset_num_timesteps=False)
    assert loaded._n_updates > updates
    assert any(not th.equal(old, new) for old, new in zip(before, loaded.policy.actor_predict.parameters(), strict=True))


def test_save_load_observation_normalizer(tmp_path):
    """The running statistics are saved with the model, and all four networks keep sharing one normalizer."""
    env = make_env()
    kwargs = dict(policy_kwargs=dict(net_arch=[16, 16], normalize_observations=True), seed=0)
    model = CGAC("MlpPolicy", env, **kwargs)
    model.learn(400)
    normalizer = model.policy.obs_normalizer
    assert normalizer is not None and normalizer.count > 400
    model.save(tmp_path / "normalized")
    loaded = CGAC.load(tmp_path / "normalized", env=env)
    assert loaded.policy.obs_normalizer is not None
    for name in ("mean", "var", "count"):
        assert th.equal(getattr(loaded.policy.obs_normalizer, name), getattr(normalizer, name)), name
    for network in (loaded.actor, loaded.actor_avg, loaded.critic, loaded.critic_target):
        assert network.features_extractor.normalizer is loaded.policy.obs_normalizer
    obs = env.reset()
    assert np.array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])
    count = float(loaded.policy.obs_normalizer.count)
    loaded.learn(100, reset_num_timesteps=False)
    assert float(loaded.policy.obs_normalizer.count) > count


def with_defaults(function, **defaults) -> tuple:
    """:return: The function's positional defaults with some replaced by name"""
    names = [p.name for p in inspect.signature(function).parameters.values() if p.default is not p.empty]
    return tuple(defaults.get(name, value) for name, value in zip(names, function.__defaults__, strict=True))


@pytest.fixture(params=["these defaults", "changed defaults"])
def release_defaults(request, monkeypatch):
    """This release's defaults, or those of a later release that changed the policy's and the algorithm's"""
    if request.param == "changed defaults":
        changed = dict(normalize_observations=True, mean_init_scale=0.01, n_bins=101, log_std_init=0.0)
        monkeypatch.setattr(CGACPolicy.__init__, "__defaults__", with_defaults(CGACPolicy.__init__, **changed))
        monkeypatch.setattr(CGAC.__init__, "__defaults__", with_defaults(CGAC.__init__, scale_rewards=True))
        assert CGAC("MlpPolicy", make_env(), **SMALL).policy.critic.support is not None  # the change is in effect
    return request.param


def test_a_saved_model_keeps_its_policy_defaults(tmp_path, monkeypatch):
    """A model saved now builds the same policy after a later release changed the policy's defaults."""
    model = CGAC("MlpPolicy", make_env(), **SMALL)
    model.learn(256)
    model.save(tmp_path / "model")
    obs = np.linspace(-1, 1, 30, dtype=np.float32).reshape(10, 3)
    expected = model.predict(obs, deterministic=True)[0]
    changed = dict(normalize_observations=True, mean_init_scale=0.01, n_bins=101)
    monkeypatch.setattr(CGACPolicy.__init__, "__defaults__", with_defaults(CGACPolicy.__init__, **changed))
    assert CGAC("MlpPolicy", make_env(), **SMALL).policy.obs_normalizer is not None  # the change is in effect
    loaded = CGAC.load(tmp_path / "model", env=make_env())
    assert loaded.policy.obs_normalizer is None and loaded.policy.critic.support is None
    np.testing.assert_allclose(loaded.predict(obs, deterministic=True)[0], expected, rtol=0, atol=1e-6)
    loaded.learn(256, reset_num_timesteps=False)


def test_policy_defaults_reach_through_keyword_arguments():
    """MultiInputPolicy passes its keyword arguments on: the defaults saved with its models are CGACPolicy's."""
    assert policy_defaults(MultiInputPolicy) == policy_defaults(CGACPolicy)
    defaults = policy_defaults(CGACPolicy)
    assert defaults["normalize_observations"] is False and "features_extractor_class" not in defaults


def test_load_a_model_of_the_previous_release(tmp_path, release_defaults):
    """A model saved by 0.1.0 with its defaults loads, acts as it did there, trains on and saves again."""
    env = make_vec_env("Pendulum-v1", n_envs=16, seed=0)
    model = CGAC.load(DATA / "cgac-0.1.0-pendulum", env=env)
    obs = np.linspace(-1, 1, 30, dtype=np.float32).reshape(10, 3)
    expected = np.load(DATA / "cgac-0.1.0-pendulum-actions.npy")
    # Equal up to float32 rounding: the CPU kinds of CI differ in their matmul kernels (AVX-512, AMX)
    np.testing.assert_allclose(model.predict(obs, deterministic=True)[0], expected, rtol=0, atol=1e-6)
    # 0.1.0's None values resolve by 0.1.0's rules (batch 64 was given; 4 critic updates, scaled Polyak rates)
    assert (model.batch_size, model.critic_updates_per_step) == (64, 4)
    assert model.tau == pytest.approx(1 - 0.995 ** np.sqrt(4096 / 8))
    assert not hasattr(model, "behaviour_kl_coef") and "stack_critics" not in model.policy_kwargs
    assert not model.scale_rewards and model.policy.obs_normalizer is None and model.policy.critic.support is None
    model.learn(16 * 4, reset_num_timesteps=False)
    model.save(tmp_path / "again")
    again = CGAC.load(tmp_path / "again", env=env)
    assert again.tau == model.tau and again.batch_size == 64


def test_load_a_model_of_0_2_0(tmp_path, release_defaults):
    """
    A model saved with 0.2.0's defaults (commit 81b6280: Pendulum-v1, 16 envs, [16, 16] networks, batch 64, 128 steps)
    loads with its own settings whatever the defaults of this release, acts as it did, and trains on.
    """
    env = make_vec_env("Pendulum-v1", n_envs=16, seed=0)
    model = CGAC.load(DATA / "cgac-0.2.0-pendulum", env=env)
    obs = np.linspace(-1, 1, 30, dtype=np.float32).reshape(10, 3)
    expected = np.load(DATA / "cgac-0.2.0-pendulum-actions.npy")
    np.testing.assert_allclose(model.predict(obs, deterministic=True)[0], expected, rtol=0, atol=1e-6)
    assert model.gamma == 0.99 and not model.scale_rewards and model.return_scale is None
    assert (model.batch_size, model.critic_updates_per_step, model.tau, model.policy_tau) == (64, 4, 0.02, 0.05)
    assert model.learning_rate == 2e-3 and model.target_entropy_beta == 1.0 and model.predict_tau is None
    assert model.policy.obs_normalizer is None and model.policy.actor_kwargs["mean_init_scale"] == 1.0
    assert model.policy.critic.support is None
    model.learn(16 * 4, reset_num_timesteps=False)


def test_a_model_with_removed_options_names_the_release():
    with pytest.raises(ValueError, match=r"entropy_schedule='reward'.*behaviour_kl_coef=1.0|behaviour_kl_coef=1.0.*v0\.1\.0"):
        CGAC.load(DATA / "cgac-0.1.0-removed-options")
    with pytest.raises(ValueError, match=r"sb3_cgac 0\.1\.0 \(git tag v0\.1\.0, commit dd52c51\)"):
        CGAC.load(DATA / "cgac-0.1.0-removed-options")


def test_load_with_fewer_envs_predicts_and_names_the_batch_to_train(tmp_path):
    """A model trained with many envs loads for evaluation on fewer; training there asks for a batch that fits."""
    model = CGAC("MlpPolicy", make_env(16), **SMALL)  # batch "auto": 512, the whole window of 16 envs
    model.save(tmp_path / "model")
    loaded = CGAC.load(tmp_path / "model", env=make_env(2))
    assert loaded.batch_size == 512
    obs = np.zeros((2, 3), np.float32)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])
    with pytest.raises(ValueError, match=r"batch_size \(512\) is larger than the buffer.*set model.batch_size"):
        loaded.learn(100)
    loaded.batch_size = 64
    loaded.learn(2 * 40)
