"""Seeds as a batch axis: each member of a batch of agents is the run it would be alone.

Three single-seed agents and a batch of three members built the same way see the same replay
samples (identical buffers with identical sampler seeds) and draw from the same generators; after
K updates their weights, Adam moments, generator states and metrics agree: bit for bit when the
batch runs its members one after another (``loop``, the CPU's default, and ``streams``, whose
members are agents of their own), to float64 rounding (float64 agents) or closely (float32) when
it maps them with vmap (CUDA's default).
"""
from __future__ import annotations

import os

import pytest
import torch

from conftest import filled_buffer, small_agent, tiny_config
from imssr import draws
from imssr.agents.batched import AgentBatch
from imssr.agents.layouts import make_batch
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


def train_both(singles: list[SACAgent], batch: AgentBatch, steps: int = STEPS):
    single_replays, batch_replays = buffers(), buffers()
    for step in range(steps):
        single_metrics = [a.update(r, step) for a, r in zip(singles, single_replays)]
        batch_metrics = batch.update(batch_replays, step)
    return single_metrics, batch_metrics


def assert_members_equal(singles, batch, single_metrics, batch_metrics, rtol: float, atol: float) -> None:
    """Every tensor of each member's state within ``atol + rtol * max|x|`` of its single run's
    (generators and counters equal), and the same metric keys with close values."""
    for i, agent in enumerate(singles):
        expected, got = flat(agent.state_dict()), flat(batch.member_state_dict(i))
        assert expected.keys() == got.keys()
        for key, x in expected.items():
            y = got[key]
            if not isinstance(x, torch.Tensor):
                assert x == y, (i, key)
            elif x.dtype.is_floating_point:
                if x.numel():
                    assert float((x - y).abs().max()) <= atol + rtol * float(x.abs().max()), (i, key)
            else:
                assert torch.equal(x, y), (i, key)
        metrics = batch.member_metrics(batch_metrics, i)
        assert metrics.keys() == single_metrics[i].keys()
        for key, value in single_metrics[i].items():
            # atol: r_int_mean is zero up to rounding (a z-score's mean)
            assert float(metrics[key]) == pytest.approx(float(value), rel=rtol, abs=1e3 * atol), (i, key)


@pytest.mark.parametrize("mode", ["loop", "streams"])
@pytest.mark.parametrize("algo", ALGOS)
def test_members_are_their_single_runs_bit_for_bit_in_turn(algo, mode):
    singles = [member(algo, s) for s in SEEDS]
    batch = make_batch([member(algo, s) for s in SEEDS], mode)
    single_metrics, batch_metrics = train_both(singles, batch)
    assert_members_equal(singles, batch, single_metrics, batch_metrics, rtol=0.0, atol=0.0)


@pytest.mark.parametrize("algo", ALGOS)
def test_members_equal_single_runs_float64_under_vmap(algo):
    singles = [member(algo, s, torch.float64) for s in SEEDS]
    batch = AgentBatch([member(algo, s, torch.float64) for s in SEEDS], mode="vmap")
    single_metrics, batch_metrics = train_both(singles, batch)
    # SODA's MLPs put a bias right before a batch norm: its gradient is zero in exact arithmetic,
    # so the bias holds nothing but rounding (about 1e-12), and Adam scales that rounding up; the
    # rest of the network stays within 1e-9 of the single run.
    rtol, atol = (1e-9, 1e-10) if "soda" in algo else (1e-10, 1e-12)
    assert_members_equal(singles, batch, single_metrics, batch_metrics, rtol=rtol, atol=atol)


FUSED = [("im-curl", {}), ("im-pad", {"own_batch": False}), ("im-soda", {})]
"""The fused schedule's three paths: the task's loss read from the critic's pass over o (CURL),
over o and o' (PAD on the RL batch), and a task that trains on passes of its own (SODA)."""


@pytest.mark.parametrize("mode", ["loop", "streams"])
@pytest.mark.parametrize("algo, aux", FUSED)
def test_fused_schedule_members_are_their_single_runs_bit_for_bit_in_turn(algo, aux, mode):
    singles = [member(algo, s, aux=aux, update_schedule="fused") for s in SEEDS]
    batch = make_batch([member(algo, s, aux=aux, update_schedule="fused") for s in SEEDS], mode)
    assert singles[0].fuse_aux == (algo != "im-soda")
    single_metrics, batch_metrics = train_both(singles, batch)
    assert_members_equal(singles, batch, single_metrics, batch_metrics, rtol=0.0, atol=0.0)


@pytest.mark.parametrize("algo, aux", FUSED)
def test_fused_schedule_members_equal_single_runs_float64_under_vmap(algo, aux):
    singles = [member(algo, s, torch.float64, aux=aux, update_schedule="fused") for s in SEEDS]
    batch = AgentBatch([member(algo, s, torch.float64, aux=aux, update_schedule="fused") for s in SEEDS], mode="vmap")
    single_metrics, batch_metrics = train_both(singles, batch)
    rtol, atol = (1e-9, 1e-10) if "soda" in algo else (1e-10, 1e-12)
    assert_members_equal(singles, batch, single_metrics, batch_metrics, rtol=rtol, atol=atol)


@pytest.mark.parametrize("algo", ["curl", "im-curl", "im-pad", "im-svea"])
def test_members_close_to_single_runs_float32_under_vmap(algo):
    singles = [member(algo, s) for s in SEEDS]
    batch = AgentBatch([member(algo, s) for s in SEEDS], mode="vmap")
    single_metrics, batch_metrics = train_both(singles, batch)
    assert_members_equal(singles, batch, single_metrics, batch_metrics, rtol=2e-3, atol=1e-6)


def test_soda_float32_weights_close_as_a_whole():
    """In float32 the rounding that Adam scales up in SODA's batch-normalised biases (see the
    float64 test) is 1e-7 rather than 1e-16: small tensors move apart by percents, the networks
    as a whole stay close."""
    singles = [member("im-soda", s) for s in SEEDS]
    batch = AgentBatch([member("im-soda", s) for s in SEEDS], mode="vmap")
    train_both(singles, batch)
    for i, agent in enumerate(singles):
        x = torch.cat([v.flatten() for v in agent.nets.state_dict().values()])
        y = torch.cat([v.flatten() for v in batch.member_state_dict(i)["nets"].values()])
        assert float((x - y).norm() / x.norm()) < 1e-4


@pytest.mark.parametrize("mode", ["loop", "vmap", "streams"])
def test_base_and_im_variant_and_betas_in_one_batch(mode):
    """CURL (intrinsic off), IM-CURL and IM-CURL with another beta_0 train as one batch, each as
    alone; the base logs no intrinsic metrics."""
    im = tiny_config("im-curl").intrinsic
    other = type(im)(**{**im.__dict__, "beta0": 0.3})
    algos_and_intrinsics = [("curl", None), ("im-curl", None), ("im-curl", other)]

    def build(i):
        algo, intrinsic = algos_and_intrinsics[i]
        return member(algo, SEEDS[i], torch.float64, **({"intrinsic": intrinsic} if intrinsic else {}))

    singles = [build(i) for i in range(3)]
    batch = make_batch([build(i) for i in range(3)], mode)
    assert batch.intrinsic_on == [False, True, True]
    single_metrics, batch_metrics = train_both(singles, batch)
    exact = mode != "vmap"
    assert_members_equal(singles, batch, single_metrics, batch_metrics, rtol=0.0 if exact else 1e-10,
                         atol=0.0 if exact else 1e-12)
    assert "beta" not in batch.member_metrics(batch_metrics, 0)
    assert float(batch.member_metrics(batch_metrics, 2)["beta"]) == pytest.approx(0.3)


@pytest.mark.parametrize("mode", ["loop", "vmap", "streams"])
@pytest.mark.parametrize("deterministic", [False, True])
def test_act_draws_each_members_own_noise(deterministic, mode):
    singles = [member("im-curl", s) for s in SEEDS]
    batch = make_batch([member("im-curl", s) for s in SEEDS], mode)
    obs = torch.randint(0, 256, (3, 9, 60, 60), dtype=torch.uint8, generator=torch.Generator().manual_seed(0))
    for _ in range(2):
        expected = [a.act(obs[i].numpy(), deterministic) for i, a in enumerate(singles)]
        got = batch.act(obs, deterministic)
        assert got.shape == (3, 2)
        for i in range(3):
            torch.testing.assert_close(got[i], torch.as_tensor(expected[i]), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("mode", ["loop", "streams"])
def test_member_state_round_trip(mode):
    """A member loaded from a single agent's state dict saves that state again."""
    single = member("im-curl", 5)
    single.update(filled_buffer(action_dim=2, seed=5, size=60), 0)
    batch = make_batch([member("im-curl", s) for s in SEEDS], mode)
    batch.load_member_state_dict(1, single.state_dict())
    expected, got = flat(single.state_dict()), flat(batch.member_state_dict(1))
    assert expected.keys() == got.keys()
    for key, x in expected.items():
        assert torch.equal(x, got[key]) if isinstance(x, torch.Tensor) else x == got[key], key
    # member 0 keeps its own weights
    torch.testing.assert_close(flat(batch.member_state_dict(0))[".nets.critic.q.q1.0.weight"],
                               member("im-curl", 1).nets.critic.q.q1[0].weight.detach())


@pytest.mark.parametrize("members, message", [
    (lambda: [member("curl", 1, compile="default"), member("curl", 2, compile="default")], "agent.compile=off"),
    (lambda: [member("curl", 1), member("curl", 2, update_schedule="fused")], "share the agent's settings"),
    (lambda: [member("curl", 1), member("curl", 2, hidden_dim=16)], "share the agent's settings"),
    (lambda: [member("curl", 1), member("soda", 2)], "auxiliary task"),
    (lambda: [member("curl", 1), member("curl+rnd", 2)], "weights of its own"),
])
def test_batches_that_cannot_be_are_refused_in_one_line(members, message):
    with pytest.raises(ImssrError, match=message) as info:
        AgentBatch(members())
    assert "\n" not in str(info.value)


def test_a_torch_random_call_with_member_generators_fails_loudly():
    gens = draws.MemberGenerators([torch.Generator().manual_seed(s) for s in SEEDS])
    with pytest.raises(TypeError):
        torch.randint(0, 10, (4,), generator=gens)
    stacked = draws.randint(10, (4,), gens, torch.device("cpu"))  # outside vmap: stacked
    expected = torch.stack([torch.randint(0, 10, (4,), generator=torch.Generator().manual_seed(s)) for s in SEEDS])
    assert torch.equal(stacked, expected)


def test_unknown_mode_is_one_line():
    with pytest.raises(ImssrError, match="unknown seed-batch layout 'grouped'; valid: auto, vmap, loop, streams"):
        make_batch([member("curl", 1)], "grouped")


def test_streams_keep_each_members_own_agent_and_refuse_stacking():
    """The streams layout steps the members' own agents (a signal with weights may sit beside a
    member without it: nothing is stacked); AgentBatch, which stacks, refuses that layout."""
    members = [member("curl", 1), member("curl+rnd", 2)]
    batch = make_batch(members, "streams")
    assert isinstance(batch, Members) and batch.members == members and batch.streams is None
    assert batch.intrinsic_on == [False, True]
    replays = buffers()[:2]
    metrics = batch.update(replays, 0)
    assert "r_int_mean" in batch.member_metrics(metrics, 1) and "r_int_mean" not in batch.member_metrics(metrics, 0)
    with pytest.raises(ImssrError, match="make_batch"):
        AgentBatch([member("curl", 1)], mode="streams")
    with pytest.raises(ImssrError, match="share the agent's settings"):
        make_batch([member("curl", 1), member("curl", 2, hidden_dim=16)], "streams")


@pytest.mark.parametrize("mode", ["loop", "vmap", "streams"])
def test_bf16_members_with_float32_q_heads(mode):
    """bf16 autocast with float32 Q heads (the bf16-fp32q runs): bit for bit in turn, close
    under vmap."""
    fields = {"precision": "bf16", "q_heads_fp32": True}
    singles = [member("im-curl", s, **fields) for s in SEEDS]
    batch = make_batch([member("im-curl", s, **fields) for s in SEEDS], mode)
    single_metrics, batch_metrics = train_both(singles, batch, steps=2)
    if mode != "vmap":
        assert_members_equal(singles, batch, single_metrics, batch_metrics, rtol=0.0, atol=0.0)
        return
    # Grouped and single convolutions round differently in bfloat16 (8 significant bits: 0.4%).
    for i, agent in enumerate(singles):
        x = torch.cat([v.flatten() for v in agent.nets.state_dict().values()])
        y = torch.cat([v.flatten() for v in batch.member_state_dict(i)["nets"].values()])
        assert float((x - y).norm() / x.norm()) < 1e-2


def test_fused_adam_is_opt_in_the_same_rule_and_kept_by_a_batch():
    assert tiny_config("im-curl").agent.fused_adam is False
    plain, fused = member("im-curl", 1), member("im-curl", 1, fused_adam=True)
    assert all(not o.defaults["fused"] for o in plain.optimizers())
    assert all(o.defaults["fused"] for o in fused.optimizers())
    for agent in (plain, fused):
        replay = buffers()[0]
        for step in range(STEPS):
            agent.update(replay, step)
    # The same update rule: only the rounding differs.
    for key, x in flat(plain.state_dict()).items():
        y = flat(fused.state_dict())[key]
        if isinstance(x, torch.Tensor) and x.dtype.is_floating_point and x.numel():
            assert float((x - y).abs().max()) <= 1e-6 + 1e-4 * float(x.abs().max()), key
    # A batch's stacked optimisers keep the members' setting, so each member is its single fused
    # run (to the rounding of the fused kernel, whose vector lanes split a stacked tensor
    # differently from a member's).
    singles = [member("im-curl", s, fused_adam=True) for s in SEEDS]
    batch = AgentBatch([member("im-curl", s, fused_adam=True) for s in SEEDS], mode="loop")
    assert all(g["fused"] for o in batch.optimizers.values() for g in o.param_groups)
    single_metrics, batch_metrics = train_both(singles, batch)
    assert_members_equal(singles, batch, single_metrics, batch_metrics, rtol=1e-5, atol=1e-9)


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
