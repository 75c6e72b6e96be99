"""An update never waits for the device: no tensor is read back to the host inside
``SACAgent.update``, for every algorithm and both schedules (checked on CPU, where the same
calls would be the syncs on a GPU)."""
import contextlib

import pytest
import torch

from conftest import filled_buffer, tiny_config
from imssr.agents import SACAgent
from imssr.algos import ALGOS

# What reads a tensor's values on the host (each waits for the device on a GPU).
HOST_READS = ("item", "__bool__", "__float__", "__int__", "cpu", "numpy", "tolist")


def small_agent(algo: str, schedule: str, precision: str = "fp32") -> SACAgent:
    """The preset on 60 px frames, 4 thin convolutions, batch 8."""
    cfg = tiny_config(algo)
    cfg.agent.update_schedule = schedule
    cfg.agent.precision = precision
    cfg.agent.encoder_layers, cfg.agent.encoder_filters, cfg.agent.crop_size = 4, 8, 52
    cfg.agent.encoder_head_layers = min(cfg.agent.encoder_head_layers, 1)
    cfg.aux.image_pool_size = 8
    return SACAgent((9, 60, 60), 2, cfg.agent, cfg.aux, cfg.intrinsic, seed=0)


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
    opts = [agent.critic_opt, agent.actor_opt, agent.alpha_opt]
    opts += [m.optimizer for m in (agent.aux, agent.signal) if m is not None and m.optimizer is not None]
    return {id(s["step"]) for opt in opts for s in opt.state.values()}


@pytest.mark.parametrize("schedule", ["sequential", "fused"])
@pytest.mark.parametrize("algo", sorted(ALGOS))
def test_update_reads_nothing_back_from_the_device(monkeypatch, algo, schedule):
    agent = small_agent(algo, schedule)
    replay = filled_buffer(60, action_dim=2, size=60)
    agent.update(replay, 0)  # creates the optimisers' state
    with host_reads_raise(monkeypatch, optimizer_step_counters(agent)):
        metrics = agent.update(replay, 2)  # critic, actor, targets and the task are all due
    assert all(torch.is_tensor(v) or isinstance(v, float) for v in metrics.values()), metrics
    assert "critic_loss" in metrics and "actor_loss" in metrics


def test_the_guard_catches_a_host_read(monkeypatch):
    with host_reads_raise(monkeypatch, set()), pytest.raises(AssertionError, match="Tensor.item"):
        torch.ones(1).item()
    with host_reads_raise(monkeypatch, set()), pytest.raises(AssertionError, match="Tensor.__bool__"):
        bool(torch.ones(1) > 0)
