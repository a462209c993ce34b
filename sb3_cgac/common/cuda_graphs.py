"""
CUDA graphs of CGAC's gradient steps (``CGAC(..., cuda_graphs=True)``): :class:`UpdateGraphs` is what the algorithm
uses; the functions below it keep the optimizers replayable across saves and loads.

With the networks of continuous control (a few layers of a few hundred units) a gradient step on a GPU is a few
hundred small kernels, and launching them from Python takes longer than running them. A CUDA graph records the
kernels of one step once and replays them with a single launch. A replayed graph reads and writes the same memory
every time, so everything a step touches must stay where it was at the capture: the minibatch is copied into static
input tensors, the networks and optimizer states are updated in place, and the learning rates are tensors that
:func:`set_learning_rate` fills in place (a float learning rate would be frozen into the graph).
"""

import contextlib
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any

import torch as th
from torch.utils import _pytree as pytree


class GraphedStep:
    """
    A step function of fixed-shape tensors, run eagerly for its first ``warmup`` calls, then captured once as a CUDA
    graph and replayed: each call copies its inputs into the graph's static inputs and returns a copy of its output.
    Inputs and output may be structures of tensors (tuples, NamedTuples, dicts): the same structure at every call.

    The eager calls run on a side stream, as capture requires: they initialise what is created lazily at a first call
    (optimizer states, cuBLAS workspaces), which must exist before the capture. They are real steps, not discarded.

    :param function: The step: it may read its arguments (tensors, or structures of them) and the state of modules
        and optimizers, which it updates in place, and returns tensors (e.g. a dict of statistics); it must not
        synchronise with the host (no ``.item()``)
    :param name: What the step is, for error messages
    :param warmup: Eager calls before the capture
    """

    def __init__(self, function: Callable[..., Any], name: str, warmup: int = 3):
        self.function = function
        self.name = name
        self.warmup = warmup
        self.eager_calls = 0
        self.graph: th.cuda.CUDAGraph | None = None
        self.static_inputs: list[th.Tensor] = []
        self.input_structure: pytree.TreeSpec | None = None
        self.static_output: Any = None
        self.side_stream: th.cuda.Stream | None = None

    def __call__(self, *inputs: Any) -> Any:
        if self.graph is None:
            if self.eager_calls < self.warmup:
                self.eager_calls += 1
                return self._side_stream_call(inputs)
            self._capture(inputs)
        leaves, structure = pytree.tree_flatten(inputs)
        if structure != self.input_structure:
            raise ValueError(f"CGAC: the {self.name} was captured for inputs {self.input_structure}, called with {structure}.")
        for static, value in zip(self.static_inputs, leaves, strict=True):
            static.copy_(value)
        assert self.graph is not None
        self.graph.replay()
        return pytree.tree_map(th.clone, self.static_output)  # the next replay overwrites the static output

    def _side_stream_call(self, inputs: Sequence[Any]) -> Any:
        if self.side_stream is None:
            self.side_stream = th.cuda.Stream()
        stream = self.side_stream
        stream.wait_stream(th.cuda.current_stream())
        with th.cuda.stream(stream):
            output = self.function(*inputs)
        th.cuda.current_stream().wait_stream(stream)
        return output

    def _capture(self, inputs: Sequence[Any]) -> None:
        leaves, self.input_structure = pytree.tree_flatten(inputs)
        self.static_inputs = [value.clone() for value in leaves]
        static_inputs = pytree.tree_unflatten(self.static_inputs, self.input_structure)
        graph = th.cuda.CUDAGraph()
        try:
            with th.cuda.graph(graph):
                self.static_output = self.function(*static_inputs)
        except RuntimeError as error:
            raise RuntimeError(
                f"CGAC: the CUDA graph capture of the {self.name} failed: {error}\nSomething in the step needs the host "
                "in the middle of it (e.g. a features extractor that checks its inputs' values). Train with "
                "cuda_graphs=False, in a new Python process: a failed capture can leave CUDA unusable in this one."
            ) from error
        self.graph = graph


def check_capturable(optimizers: Iterable[th.optim.Optimizer]) -> None:
    """Raise a ValueError that says what to do if an optimizer's steps cannot be captured in a CUDA graph."""
    for optimizer in optimizers:
        if "capturable" not in optimizer.defaults:
            raise ValueError(
                f"CGAC: cuda_graphs=True needs optimizers with a 'capturable' option; {type(optimizer).__name__} has "
                "none. Use Adam or AdamW (the default), or cuda_graphs=False."
            )


def prepare_optimizers_for_capture(optimizers: Iterable[th.optim.Optimizer], device: th.device) -> None:
    """
    Make optimizers replayable in a CUDA graph: ``capturable`` (their step counts on the device) and tensor learning
    rates on ``device``, which :func:`set_learning_rate` fills in place.

    :param optimizers: Optimizers whose class has a ``capturable`` option (Adam, AdamW, ...)
    :param device: The device of their parameters
    """
    optimizers = list(optimizers)
    check_capturable(optimizers)
    for optimizer in optimizers:
        for group in optimizer.param_groups:
            group["capturable"] = True
            if not isinstance(group["lr"], th.Tensor):
                group["lr"] = th.tensor(float(group["lr"]), device=device)


def release_param_group(group: dict) -> None:
    """Undo :func:`prepare_optimizers_for_capture` on one parameter group (or its saved copy): float learning rate,
    ``capturable=False``."""
    group["capturable"] = False
    if isinstance(group["lr"], th.Tensor):
        group["lr"] = float(group["lr"])


def release_optimizers_from_capture(optimizers: Iterable[th.optim.Optimizer]) -> None:
    """Undo :func:`prepare_optimizers_for_capture`: float learning rates, ``capturable=False``."""
    for optimizer in optimizers:
        for group in optimizer.param_groups:
            release_param_group(group)


OptimizerTensors = tuple[dict[th.Tensor, dict[str, object]], list[object]]


def keep_optimizer_tensors(optimizers: Sequence[th.optim.Optimizer]) -> list[OptimizerTensors]:
    """The state and learning rates of optimizers, as a CUDA graph of their steps reads them, before a load replaces them."""
    return [
        ({param: dict(state) for param, state in optimizer.state.items()}, [group["lr"] for group in optimizer.param_groups])
        for optimizer in optimizers
    ]


def restore_optimizer_tensors(optimizers: Sequence[th.optim.Optimizer], kept: Sequence[OptimizerTensors]) -> bool:
    """
    After ``Optimizer.load_state_dict``: copy the loaded state and learning rates into the tensors kept before it by
    :func:`keep_optimizer_tensors` and put those back, so that CUDA graphs captured before the load go on reading the
    optimizers' state.

    :return: False, and nothing changed, where the loaded state is laid out differently (e.g. saved before any update)
    """
    for optimizer, (state, lrs) in zip(optimizers, kept, strict=True):
        if set(optimizer.state) != set(state) or len(optimizer.param_groups) != len(lrs):
            return False
        if any(set(optimizer.state[param]) != set(param_state) for param, param_state in state.items()):
            return False
    for optimizer, (state, lrs) in zip(optimizers, kept, strict=True):
        for param, param_state in state.items():
            loaded = optimizer.state[param]
            for key, value in param_state.items():
                if isinstance(value, th.Tensor):
                    value.copy_(loaded[key])
                    loaded[key] = value
        for group, lr in zip(optimizer.param_groups, lrs, strict=True):
            group["capturable"] = True
            if isinstance(lr, th.Tensor):
                group["lr"] = lr.fill_(float(group["lr"]))
    return True


def set_learning_rate(optimizer: th.optim.Optimizer, learning_rate: float) -> None:
    """
    Set the learning rate of all of an optimizer's parameter groups, in place where it is a tensor (as in a
    captured CUDA graph, which reads it from the same memory at every replay).

    :param optimizer: The optimizer
    :param learning_rate: The new learning rate
    """
    for group in optimizer.param_groups:
        if isinstance(group["lr"], th.Tensor):
            group["lr"].fill_(learning_rate)
        else:
            group["lr"] = learning_rate


class UpdateGraphs:
    """
    The critic and actor updates of a model, eager or replayed as CUDA graphs (made at the first call of ``steps``),
    and what a load of saved parameters must do to the optimizers the graphs read.

    :param critic_update: The critic update function (a minibatch in, a dict of statistics out)
    :param actor_update: The actor update function, likewise (the target entropy and a minibatch in)
    :param optimizers: The optimizers the updates step (called when needed: a load may replace them)
    :param device: The device of the updates
    :param enabled: Whether to capture CUDA graphs (on a CUDA device only; elsewhere a warning and eager updates)
    """

    def __init__(
        self,
        critic_update: Callable[..., Any],
        actor_update: Callable[..., Any],
        optimizers: Callable[[], list[th.optim.Optimizer]],
        device: th.device,
        enabled: bool,
    ):
        self.critic_update = critic_update
        self.actor_update = actor_update
        self.optimizers = optimizers
        self.device = device
        self.enabled = enabled and device.type == "cuda"
        self.graphs: tuple[GraphedStep, GraphedStep] | None = None
        if enabled and not self.enabled:
            warnings.warn(f"CGAC: cuda_graphs=True has no effect on device {device}: the updates run eagerly.", stacklevel=4)
        if self.enabled:
            check_capturable(optimizers())

    def steps(self) -> tuple[Callable[..., Any], Callable[..., Any]]:
        """The critic and actor update functions: the eager ones, or their CUDA graphs."""
        if not self.enabled:
            return self.critic_update, self.actor_update
        if self.graphs is None:
            prepare_optimizers_for_capture(self.optimizers(), self.device)
            self.graphs = (GraphedStep(self.critic_update, "critic update"), GraphedStep(self.actor_update, "actor update"))
        return self.graphs

    @contextlib.contextmanager
    def loading(self) -> Iterator[None]:
        """
        Around a load of saved parameters. The networks load in place, the optimizers' states do not: the graphs read
        the old tensors, so the loaded values are copied into those (a second capture of the same parameters' updates
        failed on CUDA); where the layout differs, the graphs are dropped and captured again.
        """
        kept = keep_optimizer_tensors(self.optimizers()) if self.graphs is not None else None
        yield
        if kept is not None and not restore_optimizer_tensors(self.optimizers(), kept):
            release_optimizers_from_capture(self.optimizers())
            self.graphs = None


def plain_optimizer_states(params: dict[str, Any], names: Iterable[str]) -> None:
    """
    Give the saved state dicts of optimizers (``names`` in ``params``) float learning rates and ``capturable=False``
    whatever the training used, so that saved models load on any device.
    """
    for name in names:
        for group in params.get(name, {}).get("param_groups", []):
            if isinstance(group["lr"], th.Tensor):  # set by prepare_optimizers_for_capture
                release_param_group(group)
