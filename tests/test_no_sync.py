"""An update never waits for the device: no tensor is read back to the host inside
``SACAgent.update``, for every algorithm, both schedules and both precisions.

On CPU the check patches the Python-level ways of reading a tensor's values (``HOST_READS``:
what ``if t:``, ``float(t)``, ``int(t)``, ``range(t)``, indexing a list by ``t``, ``np.asarray(t)``
and f-strings go through); those calls are the syncs on a GPU.  Syncs that happen inside C++
(a boolean-mask index, ``nonzero``, a size taken from a tensor) cannot be seen from Python: the
CUDA test at the end runs the same update under ``torch.cuda.set_sync_debug_mode("error")``,
which sees every one, on a machine with a GPU."""
import contextlib

import pytest
import torch

from conftest import filled_buffer, small_agent
from imssr.agents import SACAgent
from imssr.algos import ALGOS

# What reads a tensor's values on the host (each waits for the device on a GPU).
HOST_READS = ("item", "__bool__", "__float__", "__int__", "__index__", "cpu", "numpy", "tolist")


@contextlib.contextmanager
def host_reads_raise(monkeypatch, allowed: set[int]):
    """Every host read of a tensor raises, except of the tensors in ``allowed`` (by id)."""
    with monkeypatch.context() as m:
        for name in HOST_READS:
            original = getattr(torch.Tensor, name)

            def guarded(self, *args, _name=name, _original=original, **kwargs):
                if id(self) in allowed:
                    return _original(self, *args, **kwargs)
                raise AssertionError(f"Tensor.{_name} called inside an update")

            m.setattr(torch.Tensor, name, guarded)
        yield


def optimizer_step_counters(agent: SACAgent) -> set[int]:
    """Adam's step counters: torch keeps them on the host by design (without ``capturable``),
    and its per-tensor and foreach Adam read them there: not a device sync."""
    return {id(s["step"]) for opt in agent.graphs.optimizers for s in opt.state.values()}


# Update paths the presets do not take: PAD on the RL batch (the fused schedule's joint o + o'
# pass, IM-PAD's reward from the training loss) and the intrinsic signal in the training loss's form.
VARIANTS = [("pad", dict(own_batch=False)), ("im-pad", dict(own_batch=False)),
            ("im-curl", dict(form="training")), ("im-soda", dict(form="training"))]


def update_without_host_reads(monkeypatch, agent: SACAgent) -> None:
    replay = filled_buffer(60, action_dim=2, size=60)
    agent.update(replay, 0)  # creates the optimisers' state
    with host_reads_raise(monkeypatch, optimizer_step_counters(agent)):
        metrics = agent.update(replay, 2)  # critic, actor, targets and the task are all due
    assert all(torch.is_tensor(v) or isinstance(v, float) for v in metrics.values()), metrics
    assert "critic_loss" in metrics and "actor_loss" in metrics


@pytest.mark.parametrize("schedule", ["sequential", "fused"])
@pytest.mark.parametrize("algo", sorted(ALGOS))
def test_update_reads_nothing_back_from_the_device(monkeypatch, algo, schedule):
    update_without_host_reads(monkeypatch, small_agent(algo, schedule))


# bf16 adds autocast regions and float32 islands (docs/performance.md): every auxiliary task
# with its own intrinsic reward, and the two other signals.
@pytest.mark.parametrize("schedule", ["sequential", "fused"])
@pytest.mark.parametrize("algo", ["im-curl", "im-soda", "im-pad", "im-svea", "curl+rnd", "curl+re3"])
def test_bf16_update_reads_nothing_back_from_the_device(monkeypatch, algo, schedule):
    update_without_host_reads(monkeypatch, small_agent(algo, schedule, "bf16"))


@pytest.mark.parametrize("schedule", ["sequential", "fused"])
@pytest.mark.parametrize("algo,aux", VARIANTS, ids=[f"{a}-{k}={v}" for a, kw in VARIANTS for k, v in kw.items()])
def test_other_update_paths_read_nothing_back(monkeypatch, algo, aux, schedule):
    agent = small_agent(algo, schedule, **aux)
    if algo.endswith("pad") and schedule == "fused":
        assert agent.fuse_aux  # the joint pass is what this case is for
    update_without_host_reads(monkeypatch, agent)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("schedule", ["sequential", "fused"])
@pytest.mark.parametrize("algo", sorted(ALGOS))
def test_cuda_update_never_synchronizes(algo, schedule):
    """CUDA's own sync detector: any synchronizing call inside the update raises."""
    agent = small_agent(algo, schedule, device="cuda")
    replay = filled_buffer(60, action_dim=2, size=60)
    agent.update(replay, 0)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")  # the host store's sample into pinned memory included
    try:
        agent.update(replay, 2)
    finally:
        torch.cuda.set_sync_debug_mode("default")


def test_the_guard_catches_a_host_read(monkeypatch):
    with host_reads_raise(monkeypatch, set()), pytest.raises(AssertionError, match="Tensor.item"):
        torch.ones(1).item()
    with host_reads_raise(monkeypatch, set()), pytest.raises(AssertionError, match="Tensor.__bool__"):
        bool(torch.ones(1) > 0)
    with host_reads_raise(monkeypatch, set()), pytest.raises(AssertionError, match="Tensor.__index__"):
        [0, 1][torch.tensor(1)]


@pytest.mark.parametrize("algo", ["im-curl", "im-soda", "curl+rnd"])
def test_an_update_under_cuda_graphs_reads_nothing_back(monkeypatch, algo):
    """The recordable path (``agent.cuda_graphs``: samples drawn first, ``beta_t`` as a tensor)
    reads nothing back either: a recording could not hold a host read."""
    update_without_host_reads(monkeypatch, small_agent(algo, agent_fields={"cuda_graphs": True}))
