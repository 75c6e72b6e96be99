"""``agent.compile`` compiles the work: Dynamo captures the conv trunks, the projections, the Q
heads and the actor's layers (a recording backend counts the convolutions it was handed), and
leaves CUDA graphs to ``agent.cuda_graphs``.  On CPU with Dynamo's ``eager`` backend: what is captured
does not depend on the backend, and no C++ compiler is needed."""
import pytest
import torch
import torch._dynamo
from torch._dynamo.utils import counters

from conftest import filled_buffer, small_agent
from imssr.agents import build
from imssr.agents.build import INDUCTOR_MODES, compile_networks
from imssr.config import COMPILE_MODES


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
    compile_networks(compiled.nets, None, backend=recorder)
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
    compile_networks(agent.nets, None, backend=recorder)
    action = agent.act(torch.randint(0, 256, (9, 60, 60), dtype=torch.uint8).numpy(), deterministic=False)
    assert action.shape == (2,)
    assert recorder.count(*CONVS) >= agent.cfg.encoder_layers and recorder.count(*LINEARS) >= 4


def test_compile_never_asks_inductor_for_cuda_graphs(monkeypatch):
    """``agent.compile`` makes kernels; CUDA graphs are ``agent.cuda_graphs``'s alone (inductor's
    own would nest inside its recordings)."""
    modes = []
    monkeypatch.setattr(build, "compile_networks", lambda nets, mode, backend="inductor": modes.append(mode))
    for mode in ("default", "max-autotune"):
        small_agent("curl", agent_fields={"compile": mode})
    assert modes == [None, "max-autotune-no-cudagraphs"]
    assert set(INDUCTOR_MODES) == set(COMPILE_MODES) - {"off"}


def test_compiled_kernels_recorded_with_the_step_change_no_number(dynamo):
    """``agent.compile`` with ``agent.cuda_graphs``: on CPU the compiled update through the static
    buffers gives the eager update's numbers."""
    replays = [filled_buffer(60, action_dim=2, size=60) for _ in range(2)]
    eager = small_agent("im-curl")
    both = small_agent("im-curl", agent_fields={"cuda_graphs": True})
    compile_networks(both.nets, None, backend="eager")
    for step in range(3):
        expected, got = eager.update(replays[0], step), both.update(replays[1], step)
        for key in expected:  # beta_t enters a recordable step as a float64 tensor: compare values
            f64 = torch.float64
            assert torch.equal(torch.as_tensor(got[key], dtype=f64), torch.as_tensor(expected[key], dtype=f64)), key
