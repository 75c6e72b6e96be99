"""``agent.cuda_graphs``: each agent step through static buffers, recorded as CUDA graphs on CUDA.

On CPU nothing is recorded, but every other part of the path runs: the replay samples drawn
before the update, ``beta_t`` as an input tensor, one set of static buffers per update path, the
outputs copied out.  So on CPU a run with it must be the run without it, bit for bit, for a single
agent and for a batch of members.  The tests marked ``cuda`` record real graphs and compare them
with eager updates; they run only where a GPU is (the prepared ``scripts/gpu_seeds.sh``).
"""
from __future__ import annotations

import pytest
import torch

from conftest import filled_buffer, small_agent
from imssr.agents.graphs import StepGraphs, set_capturable, tree_map
from imssr.agents.members import Members
from imssr.errors import ImssrError
from test_agent_batch import flat

ALGOS = ["curl", "im-curl", "soda", "im-soda", "pad", "im-pad", "svea", "im-svea", "curl+rnd", "soda+re3"]
STEPS = 5  # both update paths (actor and targets every second step), each warmed up and replayed
CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="records CUDA graphs: needs a GPU")


def run(agent, steps: int = STEPS, seed: int = 0, acts: int = 1):
    """``steps`` updates, then ``acts`` deterministic and ``acts`` sampled actions."""
    replay = filled_buffer(action_dim=2, seed=seed, size=60)
    metrics = [agent.update(replay, step) for step in range(steps)]
    actions = [agent.act(replay.sample(1)["obs"][0], deterministic=d) for d in (True, False) for _ in range(acts)]
    return metrics, actions


def assert_same_run(a, b, metrics_a, metrics_b, rtol: float = 0.0) -> None:
    sa, sb = flat(a.state_dict()), flat(b.state_dict())
    assert sa.keys() == sb.keys()
    for key, x in sa.items():
        y = sb[key]
        if key.endswith(".capturable"):  # the recorded agent's Adam is capturable, the other's not
            continue
        if isinstance(x, torch.Tensor):
            x, y = x.cpu(), y.cpu()
            if rtol == 0.0:
                assert torch.equal(x, y.to(x.dtype)), key
            elif x.numel():
                assert float((x.double() - y.double()).abs().max()) <= rtol * max(float(x.abs().max()), 1.0), key
        else:
            assert x == y, key
    for ma, mb in zip(metrics_a, metrics_b, strict=True):
        assert ma.keys() == mb.keys()
        for k in ma:
            assert float(ma[k]) == pytest.approx(float(mb[k]), rel=rtol, abs=rtol), k


@pytest.mark.parametrize("algo", ALGOS)
def test_a_single_agent_with_cuda_graphs_on_cpu_is_the_run_without(algo):
    plain, graphed = small_agent(algo, seed=3), small_agent(algo, seed=3, agent_fields={"cuda_graphs": True})
    assert graphed.graphs.enabled and not graphed.graphs.record  # CPU: nothing recorded
    metrics_plain, actions_plain = run(plain)
    metrics_graphed, actions_graphed = run(graphed)
    assert_same_run(plain, graphed, metrics_plain, metrics_graphed)
    for x, y in zip(actions_plain, actions_graphed):
        assert (x == y).all()
    # One set of static buffers per update path (the actor and targets every second step) and
    # per action pass, nothing more.
    paths = {("update", *graphed.update_key(step)) for step in range(STEPS)}
    assert len(paths) == 2 and set(graphed.graphs.steps) == paths | {("act", True), ("act", False)}


@pytest.mark.parametrize("algo", ["im-curl", "im-soda", "curl+rnd"])
def test_a_batch_with_cuda_graphs_on_cpu_is_the_batch_without(algo):
    def batch(graphs: bool) -> Members:
        # A base member beside an IM- member: beta_t enters per member.
        first = algo.removeprefix("im-")
        return Members([small_agent(a, seed=s, agent_fields={"cuda_graphs": graphs})
                        for a, s in ((first, 1), (algo, 2))])

    plain, graphed = batch(False), batch(True)
    replays = [[filled_buffer(action_dim=2, seed=s, size=60) for s in (1, 2)] for _ in range(2)]
    for step in range(STEPS):
        mp = plain.update(replays[0], step)
        mg = graphed.update(replays[1], step)
        for i in range(2):
            for k in mp[i]:  # beta_t enters a recordable step as a float64 tensor: compare values
                assert float(mp[i][k]) == float(mg[i][k]), (step, i, k)
    obs = torch.stack([torch.as_tensor(r.sample(1)["obs"][0]) for r in replays[0]]).numpy()
    assert torch.equal(plain.act(obs, True), graphed.act(obs, True))
    for i in range(2):
        a, b = flat(plain.members[i].state_dict()), flat(graphed.members[i].state_dict())
        for key, x in a.items():
            assert torch.equal(x, b[key]) if isinstance(x, torch.Tensor) else x == b[key], (i, key)


def test_static_buffers_are_reused_and_outputs_are_the_callers():
    graphs = StepGraphs(torch.device("cpu"), enabled=True)
    seen = []

    def fn(inputs):
        seen.append(inputs["x"])
        return {"y": inputs["x"] * 2}

    out1 = graphs("k", fn, {"x": torch.tensor([1.0, 2.0])})
    out2 = graphs("k", fn, {"x": torch.tensor([3.0, 4.0])})
    assert seen[0] is seen[1]  # the same static buffer, refilled
    assert out1["y"].tolist() == [2.0, 4.0] and out2["y"].tolist() == [6.0, 8.0]  # copies: not overwritten
    graphs.reset()
    assert not graphs.steps
    assert StepGraphs(torch.device("cpu"), enabled=False)("k", fn, {"x": torch.ones(1)})["y"].tolist() == [2.0]


def test_a_failed_recording_is_one_line_and_final():
    """A recording that fails (here: no CUDA to record on) stops with one line naming the setting,
    and every later step says the same: a failed capture can leave CUDA's state unusable."""
    graphs = StepGraphs(torch.device("cpu"), enabled=True, warmup=0)
    graphs.record = True  # what CUDA sets
    for _ in range(2):
        with pytest.raises(ImssrError, match=r"^agent.cuda_graphs: recording an agent step failed \(.+\); start a "
                                             r"new process with agent.cuda_graphs=false"):
            graphs("k", lambda inputs: inputs, {"x": torch.ones(1)})


def test_beta_enters_a_recordable_step_as_a_float64_tensor():
    """``beta_t`` is computed once per agent step and handed to the step: a float when it runs
    eagerly, a float64 0-dim input tensor when it may be recorded."""
    seen = []
    for graphs in (False, True):
        agent = small_agent("im-curl", seed=1, agent_fields={"cuda_graphs": graphs})
        learn = agent.learn
        agent.learn = lambda inputs, step: seen.append(inputs["beta"]) or learn(inputs, step)
        agent.update(filled_buffer(action_dim=2, size=60), 0)
    assert seen[0] == agent.schedule(0) and isinstance(seen[0], float)
    assert seen[1].dtype == torch.float64 and seen[1].shape == () and float(seen[1]) == seen[0]


def test_bf16_frozen_weight_cache_is_left_to_eager_runs():
    """The bf16 copies of frozen weights are remade when Python sees their version change, which a
    recording would freeze: under CUDA graphs each step casts them, with the same numbers."""
    from imssr.precision import FrozenBF16
    cached = small_agent("im-curl", precision="bf16", seed=2)
    recorded = small_agent("im-curl", precision="bf16", seed=2, agent_fields={"cuda_graphs": True})

    def frozen(agent):
        return sum(isinstance(getattr(m, "forward", None), FrozenBF16) for m in agent.nets.modules())

    assert frozen(cached) > 0 and frozen(recorded) == 0
    m1, a1 = run(cached)
    m2, a2 = run(recorded)
    assert_same_run(cached, recorded, m1, m2)


def test_tree_map_keeps_structure_and_non_tensors():
    tree = {"a": torch.ones(2), "b": (torch.zeros(1), 3), "c": [torch.ones(1)]}
    out = tree_map(lambda t: t + 1, tree)
    assert out["b"][1] == 3 and out["a"].tolist() == [2.0, 2.0] and isinstance(out["c"], list)


def test_set_capturable_switches_the_flag_and_keeps_cpu_steps_on_cpu():
    p = torch.nn.Parameter(torch.ones(3))
    opt = torch.optim.Adam([p])
    p.grad = torch.ones(3)
    opt.step()
    set_capturable([opt], False)  # already off: untouched
    assert opt.param_groups[0]["capturable"] is False and opt.state[p]["step"].device.type == "cpu"
    set_capturable([opt], True)
    assert opt.param_groups[0]["capturable"] is True and opt.defaults["capturable"] is True
    set_capturable([opt], False)
    assert opt.param_groups[0]["capturable"] is False and opt.state[p]["step"].dtype == torch.float32
    # A step count loaded from a checkpoint is placed again even when the flag already says so.
    set_capturable([opt], True)
    opt.state[p]["step"] = torch.tensor(3.0, dtype=torch.float64)
    set_capturable([opt], True)
    assert opt.state[p]["step"].dtype == torch.float32 and float(opt.state[p]["step"]) == 3.0


def test_a_checkpoint_loads_into_an_agent_with_or_without_cuda_graphs():
    graphed = small_agent("im-curl", seed=4, agent_fields={"cuda_graphs": True})
    run(graphed, steps=3)
    state = graphed.state_dict()
    plain = small_agent("im-curl", seed=4)
    plain.load_state_dict(state)
    again = small_agent("im-curl", seed=4, agent_fields={"cuda_graphs": True})
    again.load_state_dict(state)
    assert not again.graphs.steps  # loading forgets every recording
    m1, _ = run(plain, steps=2, seed=9)
    m2, _ = run(again, steps=2, seed=9)
    assert_same_run(plain, again, m1, m2)


# -- on a GPU -------------------------------------------------------------------------------------
@pytest.fixture
def deterministic_cudnn():
    """The same convolution algorithms in the eager and the recorded agent: cuDNN's autotuning may
    pick a nondeterministic backward, and Adam's first steps are about lr * sign(g)."""
    before = torch.backends.cudnn.deterministic
    torch.backends.cudnn.deterministic = True
    yield
    torch.backends.cudnn.deterministic = before


CUDA_CASES = [("curl", "sequential", "fp32", 1e-4), ("im-curl", "sequential", "fp32", 1e-4),
              ("im-soda", "sequential", "fp32", 1e-4), ("im-svea", "sequential", "fp32", 1e-4),
              ("curl+rnd", "sequential", "fp32", 1e-4), ("soda+re3", "sequential", "fp32", 1e-4),
              ("im-pad", "fused", "fp32", 1e-4), ("im-curl", "sequential", "bf16", 2e-2)]


@CUDA
@pytest.mark.parametrize("algo,schedule,precision,rtol", CUDA_CASES)
def test_recorded_updates_follow_the_eager_ones_on_cuda(deterministic_cudnn, algo, schedule, precision, rtol):
    """Ten updates and four actions of each kind recorded and replayed against eager ones, strict
    float32 matmuls: the same weights and generator states but for the last bits of capturable
    Adam's bias correction (bf16: those bits through bfloat16 casts)."""
    fields = {"tf32": "false"}
    eager = small_agent(algo, schedule, precision, device="cuda", seed=5, agent_fields=fields)
    graphed = small_agent(algo, schedule, precision, device="cuda", seed=5, agent_fields={**fields, "cuda_graphs": True})
    me, ae = run(eager, steps=10, acts=4)  # each path and action pass: two warm-ups, then recorded
    mg, ag = run(graphed, steps=10, acts=4)
    assert graphed.graphs.record and len(graphed.graphs.steps) == 4
    assert all(graph is not None for graph, _, _ in graphed.graphs.steps.values())
    assert_same_run(eager, graphed, me, mg, rtol=rtol)
    for x, y in zip(ae, ag):
        assert abs(x - y).max() < (1e-3 if precision == "fp32" else 5e-2)


@CUDA
def test_a_replayed_update_never_synchronizes_on_cuda():
    agent = small_agent("im-curl", device="cuda", agent_fields={"cuda_graphs": True})
    replay = filled_buffer(60, action_dim=2, size=60)
    for step in range(6):  # both paths warmed up and recorded
        agent.update(replay, step)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        agent.update(replay, 6)
        agent.update(replay, 7)
    finally:
        torch.cuda.set_sync_debug_mode("default")


@CUDA
def test_a_state_loaded_after_recording_is_recorded_again_on_cuda(deterministic_cudnn):
    """Loading replaces Adam's state tensors: the recordings are dropped and made again, and the
    run goes on as an eager agent loaded with the same state does."""
    fields = {"tf32": "false"}
    eager = small_agent("im-curl", device="cuda", seed=6, agent_fields=fields)
    graphed = small_agent("im-curl", device="cuda", seed=6, agent_fields={**fields, "cuda_graphs": True})
    run(eager, steps=8)
    run(graphed, steps=8)
    state = {k: v for k, v in eager.state_dict().items()}
    graphed.load_state_dict(state)
    eager.load_state_dict(state)
    assert not graphed.graphs.steps
    me, _ = run(eager, steps=8, seed=3)
    mg, _ = run(graphed, steps=8, seed=3)
    assert len(graphed.graphs.steps) >= 2
    assert_same_run(eager, graphed, me, mg, rtol=1e-4)


@CUDA
@pytest.mark.parametrize("n", [3, 16])
def test_a_member_among_many_on_streams_is_its_run_alone_on_cuda(deterministic_cudnn, n):
    """A batch of members: every member's recorded update replays on its own stream,
    beside the others; with deterministic cuDNN algorithms, member 1 (IM-CURL) and the last
    member are the very runs of the same seeds alone, bit for bit, and the actions of all come
    back as one tensor."""
    fields = {"tf32": "false", "cuda_graphs": True}

    def agent(i: int):
        return small_agent("curl" if i == 0 else "im-curl", seed=i + 1, device="cuda", agent_fields=fields)

    batch = Members([agent(i) for i in range(n)])
    assert len(batch.streams) == n
    alone = {i: agent(i) for i in (1, n - 1)}
    replays = [filled_buffer(action_dim=2, seed=i + 1, size=60) for i in range(n)]
    replays_alone = {i: filled_buffer(action_dim=2, seed=i + 1, size=60) for i in alone}
    for step in range(STEPS):
        metrics = batch.update(replays, step)
        expected = {i: a.update(replays_alone[i], step) for i, a in alone.items()}
        for i, m in expected.items():
            for k, v in m.items():
                assert torch.equal(v, metrics[i][k]), (i, k)
    obs = torch.stack([torch.as_tensor(r.sample(1)["obs"][0]) for r in replays_alone.values()])
    full = torch.zeros((n, *obs.shape[1:]), dtype=obs.dtype)
    for row, i in zip(obs, alone):
        full[i] = row
    for deterministic in (True, False, True):
        actions = batch.act(full.numpy(), deterministic)
        assert actions.shape == (n, 2)
        for row, (i, a) in zip(obs, alone.items()):
            assert torch.equal(actions[i].cpu(), torch.as_tensor(a.act(row.numpy(), deterministic))), (i, deterministic)
    for i, a in alone.items():
        assert_same_run(a, batch.members[i], [], [])
