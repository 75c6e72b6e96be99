"""A batch of seeds: each member of a :class:`~imssr.agents.members.Members` is the run it would
be alone.

Three single-seed agents and a batch of three members built the same way see the same replay
samples (identical buffers with identical sampler seeds) and draw from the same generators; after
K updates their weights, Adam moments, generator states and metrics agree bit for bit (on the
CPU the members run one after another).
"""
from __future__ import annotations

import os

import pytest
import torch

from conftest import filled_buffer, small_agent, tiny_config
from imssr.agents.members import Members
from imssr.agents.sac import SACAgent
from imssr.errors import ImssrError

SEEDS = (1, 2, 3)
STEPS = 4  # covers the actor's and the targets' every-2nd-step updates
ALGOS = ["curl", "im-curl", "soda", "im-soda", "pad", "im-pad", "svea", "im-svea", "curl+rnd", "soda+re3"]


def member(algo: str, seed: int, dtype: torch.dtype = torch.float32, aux: dict | None = None,
           **agent_fields) -> SACAgent:
    """A small agent of ``algo`` (conftest.small_agent) with seed ``seed``, cast to ``dtype``;
    ``aux``: fields of its auxiliary task's config."""
    intrinsic = agent_fields.pop("intrinsic", None)
    return small_agent(algo, agent_fields=agent_fields, seed=seed, dtype=dtype, intrinsic=intrinsic, **(aux or {}))


def buffers():
    return [filled_buffer(action_dim=2, seed=s, size=60) for s in SEEDS]


def flat(obj, prefix: str = "", out: dict | None = None) -> dict[str, torch.Tensor]:
    """A state dict's tensors by dotted path."""
    out = {} if out is None else out
    if isinstance(obj, torch.Tensor):
        out[prefix] = obj
    elif isinstance(obj, dict):
        for k, v in obj.items():
            flat(v, f"{prefix}.{k}", out)
    elif isinstance(obj, (list, tuple)):
        for k, v in enumerate(obj):
            flat(v, f"{prefix}.{k}", out)
    else:
        out[prefix] = obj  # settings and counters: compared with ==
    return out


def train_both(singles: list[SACAgent], batch: Members, steps: int = STEPS):
    single_replays, batch_replays = buffers(), buffers()
    for step in range(steps):
        single_metrics = [a.update(r, step) for a, r in zip(singles, single_replays)]
        batch_metrics = batch.update(batch_replays, step)
    return single_metrics, batch_metrics


def assert_members_equal(singles, batch, single_metrics, batch_metrics) -> None:
    """Every tensor of each member's state equal to its single run's (generators and counters
    too), and the same metrics."""
    for i, agent in enumerate(singles):
        expected, got = flat(agent.state_dict()), flat(batch.members[i].state_dict())
        assert expected.keys() == got.keys()
        for key, x in expected.items():
            assert torch.equal(x, got[key]) if isinstance(x, torch.Tensor) else x == got[key], (i, key)
        metrics = batch_metrics[i]
        assert metrics.keys() == single_metrics[i].keys()
        for key, value in single_metrics[i].items():
            assert torch.equal(torch.as_tensor(metrics[key]), torch.as_tensor(value)), (i, key)


@pytest.mark.parametrize("algo", ALGOS)
def test_members_are_their_single_runs_bit_for_bit(algo):
    singles = [member(algo, s) for s in SEEDS]
    batch = Members([member(algo, s) for s in SEEDS])
    assert batch.n == 3 and batch.streams is None and batch.device == torch.device("cpu")
    single_metrics, batch_metrics = train_both(singles, batch)
    assert_members_equal(singles, batch, single_metrics, batch_metrics)


FUSED = [("im-curl", {}), ("im-pad", {"own_batch": False}), ("im-soda", {})]
"""The fused schedule's three paths: the task's loss read from the critic's pass over o (CURL),
over o and o' (PAD on the RL batch), and a task that trains on passes of its own (SODA)."""


@pytest.mark.parametrize("algo, aux", FUSED)
def test_fused_schedule_members_are_their_single_runs_bit_for_bit(algo, aux):
    singles = [member(algo, s, aux=aux, update_schedule="fused") for s in SEEDS]
    batch = Members([member(algo, s, aux=aux, update_schedule="fused") for s in SEEDS])
    assert singles[0].fuse_aux == (algo != "im-soda")
    single_metrics, batch_metrics = train_both(singles, batch)
    assert_members_equal(singles, batch, single_metrics, batch_metrics)


def test_base_and_im_variants_and_betas_in_one_batch():
    """CURL (intrinsic off), IM-CURL with two beta_0 and CURL + RND (a signal with weights of its
    own) train as one batch, each as alone; a member without the intrinsic reward computes none
    and logs no intrinsic metric."""
    im = tiny_config("im-curl").intrinsic
    other = type(im)(**{**im.__dict__, "beta0": 0.3})
    plan = [("curl", None), ("im-curl", None), ("im-curl", other)]

    def build(i):
        algo, intrinsic = plan[i]
        return member(algo, SEEDS[i], **({"intrinsic": intrinsic} if intrinsic else {}))

    singles = [build(i) for i in range(3)]
    batch = Members([build(i) for i in range(3)])
    assert [m.intrinsic is not None for m in batch.members] == [False, True, True]
    single_metrics, batch_metrics = train_both(singles, batch)
    assert_members_equal(singles, batch, single_metrics, batch_metrics)
    assert "beta" not in batch_metrics[0] and "r_int_mean" not in batch_metrics[0]
    assert float(batch_metrics[2]["beta"]) == pytest.approx(0.3)
    mixed = Members([member("curl", 1), member("curl+rnd", 2)])
    metrics = mixed.update(buffers()[:2], 0)
    assert "r_int_mean" in metrics[1] and "r_int_mean" not in metrics[0]


@pytest.mark.parametrize("deterministic", [False, True])
def test_act_draws_each_members_own_noise(deterministic):
    singles = [member("im-curl", s) for s in SEEDS]
    batch = Members([member("im-curl", s) for s in SEEDS])
    obs = torch.randint(0, 256, (3, 9, 60, 60), dtype=torch.uint8, generator=torch.Generator().manual_seed(0))
    for _ in range(2):
        expected = [a.act(obs[i].numpy(), deterministic) for i, a in enumerate(singles)]
        got = batch.act(obs.numpy(), deterministic)
        assert got.shape == (3, 2)
        for i in range(3):
            assert torch.equal(got[i], torch.as_tensor(expected[i])), i


def test_a_batch_needs_members_and_one_replay_each():
    with pytest.raises(ImssrError, match="at least one member"):
        Members([])
    with pytest.raises(ImssrError, match="1 replay buffers for 2 members"):
        Members([member("curl", 1), member("curl", 2)]).update(buffers()[:1], 0)


def test_bf16_members_with_float32_q_heads():
    """bf16 autocast with float32 Q heads (the bf16-fp32q runs): bit for bit."""
    fields = {"precision": "bf16", "q_heads_fp32": True}
    singles = [member("im-curl", s, **fields) for s in SEEDS]
    batch = Members([member("im-curl", s, **fields) for s in SEEDS])
    single_metrics, batch_metrics = train_both(singles, batch, steps=2)
    assert_members_equal(singles, batch, single_metrics, batch_metrics)


def test_fused_adam_is_opt_in_and_the_same_rule():
    assert tiny_config("im-curl").agent.fused_adam is False
    plain, fused = member("im-curl", 1), member("im-curl", 1, fused_adam=True)
    assert all(not o.defaults["fused"] for o in plain.graphs.optimizers)
    assert all(o.defaults["fused"] for o in fused.graphs.optimizers)
    for agent in (plain, fused):
        replay = buffers()[0]
        for step in range(STEPS):
            agent.update(replay, step)
    # The same update rule: only the rounding differs.
    for key, x in flat(plain.state_dict()).items():
        y = flat(fused.state_dict())[key]
        if isinstance(x, torch.Tensor) and x.dtype.is_floating_point and x.numel():
            assert float((x - y).abs().max()) <= 1e-6 + 1e-4 * float(x.abs().max()), key


def test_a_batch_raises_cudas_work_queues_unless_the_user_set_them(monkeypatch):
    """CUDA reads CUDA_DEVICE_MAX_CONNECTIONS when it starts: a batch asks for 32 queues (CUDA's
    default 8 would queue several members' streams behind each other); a value the user set
    stands."""
    from imssr.agents.members import allow_concurrent_streams

    monkeypatch.setattr(torch.cuda, "is_initialized", lambda: False)  # on a GPU, a test before may have started it
    monkeypatch.delenv("CUDA_DEVICE_MAX_CONNECTIONS", raising=False)
    allow_concurrent_streams()
    assert os.environ["CUDA_DEVICE_MAX_CONNECTIONS"] == "32"
    monkeypatch.setenv("CUDA_DEVICE_MAX_CONNECTIONS", "4")
    allow_concurrent_streams()
    assert os.environ["CUDA_DEVICE_MAX_CONNECTIONS"] == "4"
