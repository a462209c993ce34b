"""
CUDA graphs of the updates (``cuda_graphs=True``). The capture itself needs a GPU (CI has none: the CUDA tests skip
there and run on a machine with one); the rest runs on the CPU.
"""

import contextlib
import pathlib

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.utils import LinearSchedule
from toy_envs import DictObsEnv  # tests/ is on sys.path under pytest

from sb3_cgac import CGAC
from sb3_cgac.buffers import CGACSamples
from sb3_cgac.common.cuda_graphs import (
    GraphedStep,
    prepare_optimizers_for_capture,
    release_optimizers_from_capture,
    set_learning_rate,
)

SMALL = dict(policy_kwargs=dict(net_arch=[16, 16]), seed=0)
needs_cuda = pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA device")


def make_env(n_envs: int = 8):
    return make_vec_env("Pendulum-v1", n_envs=n_envs, seed=0)


def test_graphed_step_takes_and_returns_structures(monkeypatch):
    """
    GraphedStep's plumbing on the CPU, with a stand-in for CUDA's graph whose replay runs the captured function again
    on the static inputs and writes its output into the static output's memory, as a replayed graph does.
    """
    step: GraphedStep

    class ReplayingGraph:
        def replay(self) -> None:
            inputs = th.utils._pytree.tree_unflatten(step.static_inputs, step.input_structure)
            th.utils._pytree.tree_map(lambda static, new: static.copy_(new), step.static_output, step.function(*inputs))

    monkeypatch.setattr(th.cuda, "CUDAGraph", ReplayingGraph)
    monkeypatch.setattr(th.cuda, "graph", lambda graph: contextlib.nullcontext())

    def update(scale: th.Tensor, data: CGACSamples) -> dict[str, th.Tensor]:
        return {"sum": (data.actions * scale).sum(), "obs": data.observations["state"].mean() + data.returns.sum()}

    def minibatch(value: float) -> CGACSamples:
        return CGACSamples({"state": th.full((4, 3), value)}, th.full((4, 2), value), th.full((4,), value), th.ones(4))

    step = GraphedStep(update, "test update", warmup=0)
    for scale, value in ((2.0, 1.0), (3.0, 5.0)):  # the capture, then a replay with new inputs
        output = step(th.tensor(scale), minibatch(value))
        expected = update(th.tensor(scale), minibatch(value))
        assert output.keys() == expected.keys() and all(th.equal(output[key], expected[key]) for key in expected)
        assert output["sum"] is not step.static_output["sum"]  # a copy: the next replay overwrites the static output
    with pytest.raises(ValueError, match="captured for inputs"):
        step(th.tensor(1.0), minibatch(1.0)._replace(observations=th.zeros(4, 3)))


def test_set_learning_rate_in_place():
    parameter = th.nn.Parameter(th.zeros(3))
    optimizer = th.optim.Adam([parameter], lr=1e-3)
    set_learning_rate(optimizer, 2e-3)
    assert optimizer.param_groups[0]["lr"] == 2e-3
    prepare_optimizers_for_capture([optimizer], th.device("cpu"))
    lr = optimizer.param_groups[0]["lr"]
    assert isinstance(lr, th.Tensor) and lr.item() == pytest.approx(2e-3)
    assert optimizer.param_groups[0]["capturable"]
    set_learning_rate(optimizer, 5e-4)
    assert optimizer.param_groups[0]["lr"] is lr, "a captured graph reads the learning rate from the same tensor"
    assert lr.item() == pytest.approx(5e-4)
    release_optimizers_from_capture([optimizer])
    assert optimizer.param_groups[0]["lr"] == pytest.approx(5e-4) and not optimizer.param_groups[0]["capturable"]


def test_optimizer_without_capturable_option():
    optimizer = th.optim.SGD([th.nn.Parameter(th.zeros(3))], lr=0.1)
    with pytest.raises(ValueError, match="needs optimizers with a 'capturable' option; SGD has none"):
        prepare_optimizers_for_capture([optimizer], th.device("cpu"))


def test_cuda_graphs_ignored_on_cpu():
    with pytest.warns(UserWarning, match="cuda_graphs=True has no effect on device cpu"):
        model = CGAC("MlpPolicy", make_env(), device="cpu", cuda_graphs=True, buffer_window=4, batch_size=32, **SMALL)
    model.learn(8 * 16)
    assert model._n_updates > 0 and model._update_graphs.graphs is None


def test_saved_optimizers_are_plain(tmp_path: pathlib.Path):
    """Models trained with CUDA graphs save float learning rates and capturable=False, so they load anywhere."""
    model = CGAC("MlpPolicy", make_env(), device="cpu", ent_coef="auto", **SMALL)
    optimizers = [model.actor.optimizer, model.critic.optimizer, model.ent_coef_optimizer]
    prepare_optimizers_for_capture(optimizers, model.device)  # as the CUDA graphs leave them
    model.save(tmp_path / "model")
    assert isinstance(model.actor.optimizer.param_groups[0]["lr"], th.Tensor), "saving leaves the live optimizers alone"
    loaded = CGAC.load(tmp_path / "model", env=make_env(), device="cpu")
    for optimizer in (loaded.actor.optimizer, loaded.critic.optimizer, loaded.ent_coef_optimizer):
        assert optimizer is not None
        group = optimizer.param_groups[0]
        assert isinstance(group["lr"], float) and not group["capturable"]
    loaded.learn(100)


def test_set_parameters_keeps_the_tensors_that_graphs_read(tmp_path: pathlib.Path):
    """On the CPU, with the optimizers prepared as the capture leaves them: what set_parameters does to a graphed model."""
    model = CGAC("MlpPolicy", make_env(), device="cpu", ent_coef="auto", buffer_window=4, batch_size=32, **SMALL)
    model.learn(8 * 16)
    model.save(tmp_path / "model")
    saved = CGAC.load(tmp_path / "model", device="cpu")
    model.learn(8 * 16)  # moves away from the saved state
    optimizers = list(model._optimizers().values())
    prepare_optimizers_for_capture(optimizers, model.device)
    model._update_graphs.graphs = (GraphedStep(model._critic_update, "critic"), GraphedStep(model._actor_update, "actor"))
    kept = [(dict(optimizer.state), [group["lr"] for group in optimizer.param_groups]) for optimizer in optimizers]
    kept_tensors = [{param: dict(param_state) for param, param_state in state.items()} for state, _ in kept]

    model.set_parameters(str(tmp_path / "model.zip"), device="cpu")
    assert model._update_graphs.graphs is not None
    for optimizer, saved_optimizer, (_, lrs), tensors in zip(
        optimizers, saved._optimizers().values(), kept, kept_tensors, strict=True
    ):
        for (param, param_state), saved_state in zip(tensors.items(), saved_optimizer.state.values(), strict=True):
            for key, tensor in param_state.items():
                assert optimizer.state[param][key] is tensor, f"{key}: a captured graph reads this tensor"
                th.testing.assert_close(tensor, saved_state[key].to(tensor.device), msg=key)
        for group, lr, saved_group in zip(optimizer.param_groups, lrs, saved_optimizer.param_groups, strict=True):
            assert group["lr"] is lr and float(lr) == pytest.approx(saved_group["lr"]) and group["capturable"]
    for param, saved_param in zip(model.policy.parameters(), saved.policy.parameters(), strict=True):
        th.testing.assert_close(param, saved_param)


def graphed_and_eager(n_envs: int = 8, env=None, **kwargs) -> tuple[CGAC, CGAC]:
    """The same run (seed, env, settings) trained eagerly and with CUDA graphs, on the GPU."""
    models = []
    kwargs = {**SMALL, "buffer_window": 4, "batch_size": 32, **kwargs}
    for cuda_graphs in (False, True):
        model_env = env() if env is not None else make_env(n_envs)
        policy = "MultiInputPolicy" if isinstance(model_env.observation_space, spaces.Dict) else "MlpPolicy"
        model = CGAC(policy, model_env, device="cuda", cuda_graphs=cuda_graphs, **kwargs)
        model.learn(n_envs * 16)
        models.append(model)
    return models[0], models[1]


@needs_cuda
@pytest.mark.parametrize(
    "kwargs",
    [
        {},
        # Nearly no action noise: the comparison does not depend on the graphs drawing the eager run's random numbers
        dict(policy_kwargs=dict(net_arch=[16], log_std_init=-10.0)),
        dict(ent_coef=0.05, policy_delay=1, learning_rate=LinearSchedule(2e-3, 1e-4, 0.5)),
        # The Ant-v5 recipe's options: the learning-rate decay (alpha's rate follows it), a third (predict) average
        dict(learning_rate=LinearSchedule(2e-3, 1e-4, 0.5), predict_tau=0.01),
        dict(ent_coef_monotone=True, policy_kwargs=dict(net_arch=[16], normalize_observations=True)),
        dict(update_precision="bfloat16"),
        dict(policy_kwargs=dict(net_arch=[16], optimizer_class=th.optim.AdamW, optimizer_kwargs=dict(foreach=True))),
        # The critic options: LayerNorm, categorical heads, the actor on the critics' mean
        dict(policy_kwargs=dict(net_arch=[16], critic_layer_norm=True, n_bins=21, actor_q_reduction="mean")),
    ],
)
def test_cuda_graphs_match_eager(kwargs):
    """Replaying the captured updates gives the eager updates' parameters, to float rounding."""
    eager, graphed = graphed_and_eager(**kwargs)
    assert graphed._update_graphs.graphs is not None
    assert all(step.graph is not None for step in graphed._update_graphs.graphs), "both updates were captured and replayed"
    assert graphed._n_updates == eager._n_updates
    for (name, expected), actual in zip(eager.policy.state_dict().items(), graphed.policy.state_dict().values(), strict=True):
        th.testing.assert_close(actual, expected, rtol=1e-4, atol=1e-5, msg=lambda text, name=name: f"{name}: {text}")
    lr = graphed.actor.optimizer.param_groups[0]["lr"]
    assert float(lr) == pytest.approx(eager.actor.optimizer.param_groups[0]["lr"])
    if eager.log_ent_coef is not None:  # alpha and its (possibly decayed) learning rate
        assert graphed.log_ent_coef is not None and graphed.ent_coef_optimizer is not None
        th.testing.assert_close(graphed.log_ent_coef.detach(), eager.log_ent_coef.detach(), rtol=1e-4, atol=1e-5)
        lr = graphed.ent_coef_optimizer.param_groups[0]["lr"]
        assert float(lr) == pytest.approx(eager.ent_coef_optimizer.param_groups[0]["lr"])


@needs_cuda
def test_cuda_graphs_need_capturable_optimizers():
    policy_kwargs = dict(net_arch=[16], optimizer_class=th.optim.SGD)
    with pytest.raises(ValueError, match="SGD has none"):
        CGAC("MlpPolicy", make_env(), device="cuda", cuda_graphs=True, policy_kwargs=policy_kwargs)


@needs_cuda
def test_cuda_graphs_dict_observations():
    eager, graphed = graphed_and_eager(n_envs=4, env=lambda: make_vec_env(DictObsEnv, n_envs=4, seed=0), batch_size=16)
    assert isinstance(graphed.observation_space, spaces.Dict) and graphed._update_graphs.graphs is not None
    assert all(step.graph is not None for step in graphed._update_graphs.graphs)
    for expected, actual in zip(eager.policy.parameters(), graphed.policy.parameters(), strict=True):
        th.testing.assert_close(actual, expected, rtol=1e-4, atol=1e-5)


@needs_cuda
def test_cuda_graphs_save_load_and_set_parameters(tmp_path: pathlib.Path):
    model = CGAC("MlpPolicy", make_env(), device="cuda", cuda_graphs=True, buffer_window=4, batch_size=32, **SMALL)
    model.learn(8 * 16)
    model.save(tmp_path / "model")
    for device in ("cpu", "cuda"):
        loaded = CGAC.load(tmp_path / "model", env=make_env(), device=device)
        loaded.learn(8 * 16)  # captured again on the GPU, eager on the CPU
        assert (loaded._update_graphs.graphs is not None) == (device == "cuda")
    # Loading parameters into a model keeps its graphs: the loaded optimizer states are copied into the tensors they read
    graphs = model._update_graphs.graphs
    model.set_parameters(str(tmp_path / "model.zip"))
    assert model._update_graphs.graphs is graphs
    before = [param.clone() for param in model.actor.parameters()]
    model.learn(8 * 16, reset_num_timesteps=False)
    assert any(not th.equal(old, new) for old, new in zip(before, model.actor.parameters(), strict=True))
    obs = make_env().reset()
    assert np.all(np.isfinite(model.predict(obs, deterministic=True)[0]))
