"""agent.precision: fp32 enters no autocast at all; bf16 runs the passes in bfloat16 and keeps
weights, optimiser state and the numerically sensitive pieces in float32."""
import numpy as np
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

import imssr
from conftest import assert_same_tensors, filled_buffer, load_script, small_agent, tiny_config, train_run
from imssr.config import apply_overrides
from imssr.errors import ImssrError
from imssr.intrinsic import IntrinsicReward
from imssr.precision import (FP32LayerNorm, FrozenBF16, bf16_slowdown, cpu_features, full_precision, native_bf16,
                             warn_if_bf16_is_slow)
from imssr.presets import make_config


@pytest.mark.parametrize("algo,schedule", [("im-curl", "sequential"), ("im-soda", "sequential"),
                                           ("im-pad", "fused"), ("svea+rnd", "sequential")])
def test_fp32_enters_no_autocast(monkeypatch, algo, schedule):
    agent = small_agent(algo, schedule)
    replay = filled_buffer(60, action_dim=2, size=60)

    def refused(*args, **kwargs):
        raise AssertionError("torch.autocast entered at agent.precision=fp32")

    monkeypatch.setattr(torch, "autocast", refused)
    agent.update(replay, 0)
    agent.act(replay.sample(1)["obs"][0], deterministic=False)


@pytest.mark.parametrize("algo,schedule", [("im-curl", "sequential"), ("im-curl", "fused"),
                                           ("im-soda", "sequential"), ("im-pad", "fused"),
                                           ("im-svea", "sequential"), ("curl+rnd", "sequential"),
                                           ("pad+re3", "sequential")])
def test_bf16_runs_the_convolutions_in_bfloat16_and_keeps_float32_state(algo, schedule):
    agent = small_agent(algo, schedule, precision="bf16")
    replay = filled_buffer(60, action_dim=2, size=60)
    conv_dtypes = set()
    hook = agent.nets.critic.encoder.trunk.convs[0].register_forward_hook(
        lambda module, args, out: conv_dtypes.add(out.dtype))
    for step in range(3):
        metrics = agent.update(replay, step)
    hook.remove()
    assert conv_dtypes == {torch.bfloat16}
    assert all(np.isfinite(float(v)) for v in metrics.values())
    # The pieces that stay float32 report float32 (the target, the TD and r_int statistics).
    assert {v.dtype for v in metrics.values() if torch.is_tensor(v)} == {torch.float32}
    states = [agent.critic_opt, agent.actor_opt, agent.alpha_opt]
    assert all(p.dtype == torch.float32 for p in agent.nets.parameters())
    assert all(t.dtype == torch.float32 for opt in states for s in opt.state.values() for t in s.values()
               if t.is_floating_point())
    action = agent.act(replay.sample(1)["obs"][0], deterministic=True)
    assert action.dtype == np.float32 and np.all(np.abs(action) <= 1)


@pytest.mark.parametrize("q_heads_fp32", [False, True])
def test_q_heads_fp32_keeps_the_q_heads_in_float32_under_bf16(q_heads_fp32):
    """agent.q_heads_fp32 reaches the online and target Q heads: their layers run in float32 while
    the convolutions stay bfloat16; without it, the heads run in bfloat16 like every layer."""
    agent = small_agent("im-curl", "sequential", "bf16", agent_fields={"q_heads_fp32": q_heads_fp32})
    replay = filled_buffer(60, action_dim=2, size=60)
    seen = {"conv": set(), "q": set(), "target q": set()}
    layers = {"conv": agent.nets.critic.encoder.trunk.convs[0], "q": agent.nets.critic.q.q1[0],
              "target q": agent.nets.critic_target.q.q2[-1]}
    hooks = [layer.register_forward_hook(lambda m, args, out, k=k: seen[k].add(out.dtype))
             for k, layer in layers.items()]
    for step in range(3):
        metrics = agent.update(replay, step)
    for hook in hooks:
        hook.remove()
    heads = torch.float32 if q_heads_fp32 else torch.bfloat16
    assert seen == {"conv": {torch.bfloat16}, "q": {heads}, "target q": {heads}}
    assert all(np.isfinite(float(v)) for v in metrics.values())


def test_q_heads_fp32_changes_nothing_at_fp32():
    """At fp32 the setting is a no-op: the same updates, bit for bit."""
    states = []
    for q_heads_fp32 in (False, True):
        agent = small_agent("im-curl", "sequential", agent_fields={"q_heads_fp32": q_heads_fp32})
        replay = filled_buffer(60, action_dim=2, size=60)
        for step in range(3):
            agent.update(replay, step)
        states.append(agent.nets.state_dict())
    assert assert_same_tensors(states[0], states[1]) > 0


def test_bf16_agrees_with_fp32_to_bfloat16_rounding():
    """Same seed, same batch: the first critic loss and the trunk features of both precisions."""
    replay = filled_buffer(60, action_dim=2, size=60)
    obs = torch.as_tensor(replay.sample(8)["obs"])[:, :, :52, :52]
    losses, features = [], []
    for precision in ("fp32", "bf16"):
        agent = small_agent("curl", "sequential", precision)
        with torch.no_grad(), agent.autocast():
            features.append(agent.nets.critic.encoder.trunk(obs).float())
        replay.rng = np.random.default_rng(0)  # the same batch for both
        losses.append(float(agent.update(replay, 0)["critic_loss"]))
    assert features[1].dtype == torch.float32
    rel = (features[0] - features[1]).abs().max() / features[0].abs().max()
    assert 0 < rel < 0.05
    assert losses[1] == pytest.approx(losses[0], rel=0.1)


def test_float32_islands_under_autocast():
    x = torch.randn(4, 16)
    ln, w = FP32LayerNorm(16), torch.randn(16, 16)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        low = x @ w
        assert low.dtype == torch.bfloat16
        assert ln(low).dtype == torch.float32
        with full_precision(low):
            assert (low.float() @ w).dtype == torch.float32
        bonus, stats = IntrinsicReward(make_config("im-curl", "cartpole_swingup").intrinsic)(low[:, 0], 0.05)
        assert bonus.dtype == torch.float32 and stats["r_int_raw"].dtype == torch.float32


def test_precision_is_validated_and_bf16_is_one_override():
    cfg = apply_overrides(make_config("im-curl", "cartpole_swingup"), ["agent.precision=bf16"])
    assert cfg.validate().agent.precision == "bf16"
    assert make_config("im-curl", "cartpole_swingup").agent.precision == "fp32"  # the paper's
    with pytest.raises(ImssrError, match="agent.precision must be one of fp32, bf16"):
        apply_overrides(make_config("curl", "cartpole_swingup"), ["agent.precision=fp16"]).validate()


def test_native_bfloat16_is_read_from_cpuinfo_and_only_cpu_bf16_can_be_slow():
    assert native_bf16("processor\t: 0\nflags\t\t: fpu sse avx512f avx512_bf16 avx512_vnni\n")
    assert native_bf16("Features\t: fp asimd bf16 i8mm\n")
    assert not native_bf16("flags\t\t: fpu sse avx2 avx512f avx512bw\n")
    assert cpu_features(INTEL_NO_AMX) == ("GenuineIntel", frozenset({"fpu", "avx2", "avx512f", "avx512_bf16"}))
    assert cpu_features("Features\t: fp asimd bf16\n") == ("", frozenset({"fp", "asimd", "bf16"}))
    assert warn_if_bf16_is_slow(torch.device("cpu"), "fp32") is None
    assert warn_if_bf16_is_slow(torch.device("cuda"), "bf16") is None


INTEL_NO_AMX = "processor\t: 0\nvendor_id\t: GenuineIntel\nflags\t\t: fpu avx2 avx512f avx512_bf16\n"
AVX512 = frozenset({"avx2", "avx512f", "avx512_bf16"})


@pytest.mark.parametrize("vendor, flags, why", [
    ("AuthenticAMD", AVX512, None),                                 # Zen 4: 0.42-0.46x of fp32's time
    ("GenuineIntel", AVX512 | {"amx_bf16", "amx_tile"}, None),      # AMX
    ("GenuineIntel", AVX512, "no-amx"),                             # a Xeon with avx512_bf16 alone: 1.14-1.23x
    ("CentaurHauls", AVX512, "no-amx"),                             # not measured to gain
    ("AuthenticAMD", frozenset({"avx2", "avx512f"}), "emulated"),   # Zen 3 / AVX-512 without bf16
    ("GenuineIntel", frozenset({"avx2"}), "emulated"),
    ("", frozenset({"fp", "asimd", "bf16"}), None),                 # Arm's bf16: native, not measured
    ("", frozenset(), "emulated"),
])
def test_bf16_is_expected_to_gain_only_on_amd_with_avx512_bf16_or_intel_with_amx(vendor, flags, why):
    assert bf16_slowdown(vendor, flags) == why


@pytest.mark.parametrize("cpuinfo", [None, INTEL_NO_AMX, "vendor_id\t: AuthenticAMD\nflags\t\t: avx2 avx512_bf16\n",
                                     "vendor_id\t: AuthenticAMD\nflags\t\t: avx2\n"])
def test_the_slow_bf16_warning_is_printed_once_and_only_where_bf16_is_expected_slower(cpuinfo, monkeypatch, capsys):
    import imssr.precision as precision

    monkeypatch.setattr(precision, "cpu_info", lambda: cpuinfo)
    monkeypatch.setattr(precision, "_warned_slow_bf16", False)
    lines = [warn_if_bf16_is_slow(torch.device("cpu"), "bf16") for _ in range(3)]
    printed = capsys.readouterr().err.splitlines()
    if cpuinfo is None or "AuthenticAMD" in cpuinfo and "avx512_bf16" in cpuinfo:  # cannot tell, or gains
        assert lines == [None, None, None] and printed == []
        return
    assert lines[0] == lines[1] == lines[2] and lines[0].startswith("imssr: warning: agent.precision=bf16 on a CPU ")
    assert lines[0].endswith(": expect it slower than fp32 here") and printed == [lines[0]]
    if cpuinfo == INTEL_NO_AMX:
        assert "with avx512_bf16 but without AMX" in lines[0]
    else:
        assert "without native bfloat16 (no avx512_bf16/AMX; torch sees " in lines[0]


class CastCount(TorchDispatchMode):
    """Counts the dtype casts (``aten._to_copy``) dispatched while active."""

    def __init__(self):
        super().__init__()
        self.casts = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.casts += func.overloadpacket is torch.ops.aten._to_copy
        return func(*args, **(kwargs or {}))


@pytest.mark.parametrize("algo", ["curl", "im-soda"])
def test_bf16_casts_frozen_weights_once_per_change_with_the_same_numbers(monkeypatch, algo):
    """The target networks' (and SODA's target's) bf16 copies are made again only after an EMA
    step: fewer casts per update than autocast alone, and bit for bit the same update."""
    import imssr.agents.build as build

    cache = build.cache_frozen_weights
    agents, casts, metrics = {}, {}, {}
    for cached in (False, True):
        monkeypatch.setattr(build, "cache_frozen_weights", cache if cached else lambda *modules: 0)
        agent = agents[cached] = small_agent(algo, "sequential", precision="bf16")
        assert any(isinstance(m.__dict__.get("forward"), FrozenBF16) for m in agent.nets.modules()) == cached
        replay = filled_buffer(60, action_dim=2, size=60)
        agent.update(replay, 0)
        with CastCount() as count:
            for step in range(1, 5):  # two EMA periods (target_update_every = 2)
                metrics[cached] = agent.update(replay, step)
        casts[cached] = count.casts
    # Each frozen conv or linear layer's weight and bias: cast at every call without the cache.
    assert casts[True] < casts[False] - 8, casts
    for (k, v), (_, w) in zip(agents[False].nets.state_dict().items(), agents[True].nets.state_dict().items()):
        assert torch.equal(v, w), k
    for key, value in metrics[False].items():
        assert torch.equal(torch.as_tensor(metrics[True][key]), torch.as_tensor(value)), key


def test_fp32_agents_keep_the_layers_own_forward():
    agent = small_agent("im-soda", "sequential")
    assert not any("forward" in m.__dict__ for m in agent.nets.modules())
    assert not any("forward" in m.__dict__ for m in agent.aux.modules())


def test_bf16_fidelity_measures_against_fp32_on_the_same_states_and_actions(tmp_path, capsys):
    """scripts/bf16_fidelity.py on a trained (tiny) run: fp32 against itself agrees exactly (same
    states, candidates, weights: no regret, every gradient sign kept); bf16 is measured on the same
    ones; the CLI prints a row per checkpoint and part and refuses a missing run in one line."""
    out_dir = tmp_path / "run"
    train_run(tiny_config("curl", steps=80, eval_every_steps=0, checkpoint_every_steps=80), out_dir)
    fidelity = load_script("scripts/bf16_fidelity.py")
    run = imssr.load_run(str(out_dir))
    x = fidelity.states(run, episodes=2, per_episode=3, seed=0)
    assert x.shape[0] == 6 and x.dtype == torch.uint8
    same = fidelity.measure(run, x, 5, 0, encoder="fp32", head="fp32")
    assert (same["regret_share"], same["regret_median"], same["sign_same"], same["cosine_median"]) == (0, 0, 1, 1)
    assert same["spread_median"] > 0
    bf16 = fidelity.measure(run, x, 5, 0, encoder="bf16", head="bf16")
    assert 0 <= bf16["sign_same"] <= 1 and 0 <= bf16["regret_median"] <= 1 and bf16["q_median"] == same["q_median"]
    # The candidates of a one-dimensional action are an even grid of [-1, 1].
    grid = fidelity.candidates(torch.zeros(2, 1), 5, torch.Generator().manual_seed(0))
    assert torch.equal(grid[0, :, 0], torch.tensor([-1.0, -0.5, 0.0, 0.5, 1.0]))

    assert fidelity.main([str(out_dir), "--episodes", "1", "--states-per-episode", "3", "--actions", "3",
                          "--split"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| 80 |")]
    assert [r.split(" | ")[1] for r in rows] == ["encoder and Q heads", "encoder only", "Q heads only"]
    assert fidelity.main([str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bf16_fidelity: ") and err.count("\n") == 1


def test_a_pass_after_an_optimizer_step_reads_the_new_weights_under_bf16():
    """Inside one update's autocast region, the actor's pass on the critic's trunk after the
    critic's step casts the stepped weights, not autocast's cached casts of the old ones."""
    from imssr.precision import optimizer_step

    agent = small_agent("curl", "sequential", precision="bf16")
    trunk = agent.nets.critic.encoder.trunk
    x = torch.randint(0, 256, (4, 9, 52, 52), dtype=torch.uint8)
    with agent.autocast():
        before = trunk(x)
        optimizer_step(before.float().pow(2).mean(), agent.critic_opt)
        after = trunk(x)
    with agent.autocast():  # a fresh region: casts of the current weights
        fresh = trunk(x)
    assert not torch.equal(before, after)
    assert torch.equal(after, fresh)
