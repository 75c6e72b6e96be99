"""``agent.compile`` compiles the work: Dynamo captures the conv trunks, the projections, the Q
heads and the actor's layers (a recording backend counts the convolutions it was handed), and
the CUDA-graph modes mark each step.  On CPU with Dynamo's ``eager`` backend: what is captured
does not depend on the backend, and no C++ compiler is needed."""
import pytest
import torch
import torch._dynamo
from torch._dynamo.utils import counters

from conftest import filled_buffer, small_agent
from imssr.agents.sac import CUDA_GRAPH_MODES, uses_cuda_graphs


class Recorder:
    """A Dynamo backend that runs each captured graph as it is and keeps it."""

    def __init__(self):
        self.graphs: list[torch.fx.GraphModule] = []

    def __call__(self, gm: torch.fx.GraphModule, example_inputs):
        self.graphs.append(gm)
        return gm.forward

    def count(self, *targets) -> int:
        return sum(node.target in targets for gm in self.graphs for node in gm.graph.nodes)


CONVS = (torch.conv2d, torch.nn.functional.conv2d)
LINEARS = (torch._C._nn.linear, torch.nn.functional.linear)


@pytest.fixture
def dynamo():
    torch._dynamo.reset()
    counters.clear()
    yield
    torch._dynamo.reset()
    counters.clear()


@pytest.mark.parametrize("algo,schedule", [("im-curl", "sequential"), ("pad", "fused")])
def test_compile_captures_the_conv_trunk_and_changes_no_number(dynamo, algo, schedule):
    # Each agent samples its own buffer: a sample advances the buffer's generator.
    replays = [filled_buffer(60, action_dim=2, size=60) for _ in range(2)]
    eager, compiled = small_agent(algo, schedule), small_agent(algo, schedule)
    recorder = Recorder()
    compiled._compile(None, backend=recorder)
    for step in range(2):
        expected, got = eager.update(replays[0], step), compiled.update(replays[1], step)
        assert set(got) == set(expected)
        for key in expected:
            assert torch.equal(torch.as_tensor(got[key]), torch.as_tensor(expected[key])), key
    assert counters["frames"]["ok"] > 0 and counters["stats"]["unique_graphs"] > 0
    layers = compiled.cfg.encoder_layers
    # Every convolution of the trunk is in a captured graph (shared layers and head, online and
    # target encoders), and so are the linear layers of the projections, Q heads and actor.
    assert recorder.count(*CONVS) >= layers
    assert recorder.count(*LINEARS) >= 1 + 6 + 3


def test_act_runs_compiled_layers(dynamo):
    agent = small_agent("curl", "sequential")
    recorder = Recorder()
    agent._compile(None, backend=recorder)
    action = agent.act(torch.randint(0, 256, (9, 60, 60), dtype=torch.uint8).numpy(), deterministic=False)
    assert action.shape == (2,)
    assert recorder.count(*CONVS) >= agent.cfg.encoder_layers and recorder.count(*LINEARS) >= 4


def test_cuda_graph_modes_mark_every_act_and_update(monkeypatch):
    marks = []
    monkeypatch.setattr(torch.compiler, "cudagraph_mark_step_begin", lambda: marks.append(1))
    agent = small_agent("curl", "sequential")
    assert agent.cuda_graphs is False  # CPU: no CUDA graphs, nothing marked
    agent.update(filled_buffer(60, action_dim=2, size=60), 0)
    assert marks == []
    agent.cuda_graphs = True  # what a CUDA agent with a CUDA-graph mode sets
    agent.update(filled_buffer(60, action_dim=2, size=60), 1)
    agent.act(torch.zeros(9, 60, 60, dtype=torch.uint8).numpy(), deterministic=True)
    assert len(marks) == 2
    assert CUDA_GRAPH_MODES == ("reduce-overhead", "max-autotune")


def test_cuda_graphs_only_on_cuda_in_the_cuda_graph_modes():
    """The rule the agent's :attr:`cuda_graphs` comes from: CUDA and reduce-overhead or
    max-autotune; never on a CPU, never in the default mode or eager."""
    for mode in ("off", "default", "reduce-overhead", "max-autotune"):
        assert uses_cuda_graphs(torch.device("cpu"), mode) is False
        for cuda in (torch.device("cuda"), torch.device("cuda:1")):
            assert uses_cuda_graphs(cuda, mode) is (mode in ("reduce-overhead", "max-autotune"))
