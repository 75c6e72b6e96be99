"""Each agent step as a few CUDA graph launches (``agent.cuda_graphs``).

An update of CURL issues about 330 ATen ops (about 385 kernels), each launched from Python; on
a GPU the host spends several times longer issuing them than the GPU spends running them
(docs/performance.md).  :class:`StepGraphs` records the kernels of one update (forward,
backward and every optimiser step) or of one action pass once, as a ``torch.cuda.CUDAGraph``,
and then replays the recording: one launch for the whole update.

A recording replays exactly what it recorded, so what it captures must be the same every time:

* **Static inputs.**  The function reads only the tensors it is given (the replay sample,
  ``beta_t``); :class:`StepGraphs` copies each call's values into the buffers the recording
  reads.  Everything else it touches lives at a fixed address: weights, Adam's moments and step
  counts (``capturable``), target weights.
* **One recording per path.**  An update branches on the agent step (the actor every second
  step, ...); the caller names the branches taken (``key``) and each key gets its own recording.
* **Random draws from registered generators.**  Crops, policy noise and the intrinsic views
  come from the agent's own ``torch.Generator``s; each is registered with the recording, so a
  replay draws fresh numbers and moves the generator on, as an eager call would.
* **No host read inside.**  Metrics stay on the device; a replay's outputs are copied out of
  the recording's buffers before the next replay overwrites them.

On CUDA, the first ``warmup`` calls of a key run eagerly on a side stream (torch's advice before
a capture: lazy initialisations, Adam's state, cuDNN's choice of algorithms), the next records
and replays.  Elsewhere there is nothing to record: the same function runs eagerly on the same
static buffers, so the CPU tests go through every step of the path but the recording itself.
"""
from __future__ import annotations

from typing import Any, Callable, Hashable, Iterable, Optional, Sequence

import torch

from imssr.errors import ImssrError

Tree = Any
"""A tensor, or a dict / tuple / list of trees (a step's inputs and outputs); other leaves pass
through as they are."""


def tree_map(fn: Callable[..., Any], tree: Tree, *others: Tree) -> Tree:
    """``fn`` applied to every tensor of ``tree`` (and the matching leaves of ``others``)."""
    if isinstance(tree, dict):
        return {k: tree_map(fn, v, *(o[k] for o in others)) for k, v in tree.items()}
    if isinstance(tree, (tuple, list)):
        return type(tree)(tree_map(fn, *parts) for parts in zip(tree, *others, strict=True))
    if isinstance(tree, torch.Tensor):
        return fn(tree, *others)
    return tree


def set_capturable(optimizers: Iterable[torch.optim.Optimizer], on: bool) -> None:
    """Switch Adam's ``capturable`` flag on (its step count on the weights' device, its bias
    correction computed there: what a recording needs) or off, and move the step counts where
    the flag wants them.  A checkpoint keeps the flag it was saved with, and a loaded step count
    sits where the checkpoint was mapped (the CPU), so a resumed or evaluated agent sets both
    again after loading."""
    for opt in optimizers:
        opt.defaults["capturable"] = on
        if on:
            # Warm-up steps run capturable Adam outside a recording on purpose: torch's warning
            # that this may be slow is for optimisers that are never recorded.
            opt._warned_capturable_if_run_uncaptured = True
        for group in opt.param_groups:
            group["capturable"] = on
            for p in group["params"]:
                state = opt.state.get(p, {})
                step = state.get("step")
                if isinstance(step, torch.Tensor):
                    # Fused Adam keeps its step count on the device either way.
                    device = p.device if on or group.get("fused") else torch.device("cpu")
                    state["step"] = step.to(device, torch.float32)


def _clear_cublas_workspaces() -> None:
    """Drop cuBLAS's workspaces (CUDA builds of torch; the next matmul allocates one again)."""
    clear = getattr(torch._C, "_cuda_clearCublasWorkspaces", None)
    if clear is not None:
        clear()


class StepGraphs:
    """Runs a step function, recorded as a CUDA graph per key on CUDA (see the module's doc)."""

    def __init__(self, device: torch.device, enabled: bool, warmup: int = 2,
                 generators: Sequence[torch.Generator] = (), optimizers: Sequence[torch.optim.Optimizer] = ()):
        self.device, self.enabled, self.warmup = torch.device(device), enabled, warmup
        self.generators = tuple(generators)
        """What a recording registers: every generator the step draws from."""
        self.optimizers = tuple(optimizers)
        """Every optimiser the step steps, made capturable (:func:`set_capturable`) before each
        warm-up and recording."""
        self.record = self.enabled and self.device.type == "cuda"
        """Whether calls are recorded (CUDA); otherwise they run eagerly on the static buffers."""
        self.calls: dict[Hashable, int] = {}
        self.steps: dict[Hashable, tuple[Optional[torch.cuda.CUDAGraph], Tree, Tree]] = {}
        """Per key: the recording (None off CUDA), its static inputs and its outputs."""
        self.failed: Optional[str] = None
        """Why a recording failed: a failed capture can leave CUDA's state unusable, so no step of
        this process records or runs again."""

    def __call__(self, key: Hashable, fn: Callable[[Tree], Tree], inputs: Tree) -> Tree:
        """``fn(inputs)``: directly when disabled; else through ``key``'s static buffers (and
        recording).  The outputs are the caller's own (copies of the recording's)."""
        if not self.enabled:
            return fn(inputs)
        if self.failed is not None:
            raise ImssrError(self.failed)
        if key not in self.steps:
            calls = self.calls.get(key, 0)
            self.calls[key] = calls + 1
            if self.record:
                set_capturable(self.optimizers, True)
            if self.record and calls < self.warmup:
                return self._warm(fn, inputs)
            static = tree_map(lambda t: t.clone(), inputs)
            if not self.record:
                self.steps[key] = (None, static, None)
            else:
                # A capture records the kernels without running them: the replay below runs
                # this call's step.
                self.steps[key] = self._capture(fn, static)
        graph, static, outputs = self.steps[key]
        tree_map(lambda s, t: s.copy_(t, non_blocking=True), static, inputs)
        if graph is None:
            outputs = fn(static)
        else:
            graph.replay()
        return tree_map(lambda t: t.clone(), outputs)

    def reset(self) -> None:
        """Forget every recording: state loaded into the agent may sit at new addresses (an
        optimiser's ``load_state_dict`` replaces its state tensors), which a recording would
        never read."""
        self.calls.clear()
        self.steps.clear()

    def _warm(self, fn, inputs: Tree) -> Tree:
        side = torch.cuda.Stream(self.device)
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(side):
            out = fn(inputs)
        torch.cuda.current_stream(self.device).wait_stream(side)
        return out

    def _capture(self, fn, static: Tree) -> tuple[torch.cuda.CUDAGraph, Tree, Tree]:
        try:
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.device(self.device):
                for generator in self.generators:
                    graph.register_generator_state(generator)
            # cuBLAS keeps one workspace per stream, and a recording keeps the address of the one
            # it was made with: recordings made on one stream would share it, members of a batch
            # on streams of their own (agents/members.py) would race on it when they replay at the
            # same time, and destroying one recording would free it under the others.  Cleared
            # before and after, the recording allocates a workspace of its own in its own pool
            # (as torch's inductor does for its recordings).
            _clear_cublas_workspaces()
            try:
                with torch.cuda.graph(graph, capture_error_mode="thread_local"):
                    outputs = fn(static)
            finally:
                _clear_cublas_workspaces()
        except Exception as e:  # the step ran eagerly in the warm-up: what fails here is the recording
            # When the step fails inside the recording, ending the capture fails too: the step's
            # own error is then the context of the one raised.
            cause = e.__context__ if isinstance(e.__context__, Exception) else e
            reason = (str(cause).strip().splitlines() or [type(cause).__name__])[0]
            self.failed = (f"agent.cuda_graphs: recording an agent step failed ({reason}); start a new process "
                           "with agent.cuda_graphs=false to run the steps eagerly")
            raise ImssrError(self.failed) from e
        return graph, static, outputs
