"""SAC agent: actions, determinism, save/load round trip, update schedule."""
import numpy as np
import pytest
import torch

from conftest import assert_same_nets, filled_buffer, small_agent, tiny_config
from imssr.agents import make_agent
from imssr.augmentations import center_crop
from imssr.batch import NextObsContext
from imssr.errors import ImssrError


def _agent(seed=0, algo="curl"):
    cfg = tiny_config(algo)
    return make_agent((9, 100, 100), 2, cfg.agent, cfg.aux, cfg.intrinsic, seed=seed)


def test_actions_in_bounds_and_deterministic_mode():
    agent = _agent()
    obs = np.random.default_rng(0).integers(0, 256, (9, 100, 100), dtype=np.uint8)
    a = agent.act(obs, deterministic=True)
    assert a.shape == (2,) and a.dtype == np.float32 and np.all(np.abs(a) <= 1)
    assert np.array_equal(a, agent.act(obs, deterministic=True))
    samples = np.stack([agent.act(obs, deterministic=False) for _ in range(20)])
    assert np.all(np.abs(samples) <= 1) and samples.std(0).min() > 0


def test_same_seed_same_updates():
    a, b = _agent(seed=3), _agent(seed=3)
    buf_a, buf_b = filled_buffer(action_dim=2, seed=1), filled_buffer(action_dim=2, seed=1)
    for s in range(4):
        a.update(buf_a, s)
        b.update(buf_b, s)
    assert_same_nets(a, b)


def test_state_dict_round_trip_continues_identically():
    a = _agent(seed=1)
    buf = filled_buffer(action_dim=2, seed=2)
    for s in range(3):
        a.update(buf, s)
    b = _agent(seed=99)
    b.load_state_dict(a.state_dict())
    buf_b = filled_buffer(action_dim=2, seed=2)
    buf_b.rng.bit_generator.state = buf.rng.bit_generator.state
    for s in range(3, 6):
        a.update(buf, s)
        b.update(buf_b, s)
    assert_same_nets(a, b)


def test_update_schedule_actor_every_two_steps_and_actor_never_trains_convs():
    agent = _agent()
    buf = filled_buffer(action_dim=2)
    m0, m1 = agent.update(buf, 0), agent.update(buf, 1)
    assert "actor_loss" in m0 and "actor_loss" not in m1
    assert "critic_loss" in m0 and "critic_loss" in m1 and "aux_loss" in m1
    trunk_ids = {id(p) for p in agent.nets.critic.encoder.trunk.parameters()}
    actor_ids = {id(p) for g in agent.actor_opt.param_groups for p in g["params"]}
    assert not trunk_ids & actor_ids


def test_target_networks_track_with_their_own_rates():
    agent = _agent()
    n = agent.nets
    for p in n.critic.parameters():
        p.data.add_(1.0)
    before_q = [p.clone() for p in n.critic_target.q.parameters()]
    before_enc = [p.clone() for p in n.critic_target.encoder.parameters()]
    agent.soft_update_targets()
    dq = (next(n.critic_target.q.parameters()) - before_q[0]).mean().item()
    de = (next(n.critic_target.encoder.parameters()) - before_enc[0]).mean().item()
    assert abs(dq - 0.01) < 1e-4 and abs(de - 0.05) < 1e-4


def test_task_optimisers_keep_the_parameter_order_of_saved_checkpoints():
    """Adam's saved state is per parameter position: each task's optimiser lists its parameters
    as imssr's checkpoints always did, so older checkpoints resume."""
    for algo, old_order in (
            ("curl", lambda a: [a.aux.W, *a.nets.critic.encoder.parameters()]),
            ("pad", lambda a: [*a.nets.critic.encoder.trunk.convs.parameters(), *a.aux.parameters()]),
            ("soda", lambda a: [*a.nets.critic.encoder.trunk.parameters(), *a.aux.projection.parameters(),
                                *a.aux.predictor.parameters()])):
        agent = _agent(algo=algo)
        (group,) = agent.aux.optimizer.param_groups
        assert [id(p) for p in group["params"]] == [id(p) for p in old_order(agent)], algo
    assert _agent(algo="svea").aux.optimizer is None  # no loss of its own, nothing to step


def test_deterministic_policy_output_is_the_mean_without_a_sample():
    agent = _agent()
    crop = agent.cfg.crop_size
    obs = torch.as_tensor(filled_buffer(action_dim=2).sample(4)["obs"][:, :, :crop, :crop])
    with torch.no_grad():
        trunk = agent.nets.critic.encoder.trunk(obs)
    state = agent.noise_gen.get_state()
    policy = agent.nets.actor(trunk, generator=agent.noise_gen, sample=False)
    assert policy.action is policy.mean and policy.log_prob is None
    assert torch.equal(agent.noise_gen.get_state(), state)  # no noise drawn
    sampled = agent.nets.actor(trunk, generator=agent.noise_gen)
    assert sampled.log_prob.shape == (4, 1) and not torch.equal(sampled.action, sampled.mean)


def test_intrinsic_signal_is_the_raw_per_sample_signal_of_the_next_observation():
    agent = _agent(algo="im-curl")
    batch = agent.to_batch(filled_buffer(action_dim=2).sample(8))
    enc = agent.encode(batch)
    gen = agent.gen.get_state()
    signal = agent.intrinsic_signal(batch, enc)
    assert signal.shape == (8,) and not signal.requires_grad
    assert torch.equal(agent.gen.get_state(), gen)  # the base algorithm's stream is untouched
    ctx = NextObsContext(batch=batch, enc=enc, generator=torch.Generator(), form=agent.intrinsic.cfg.form)
    torch.testing.assert_close(signal, agent.aux.intrinsic_loss(ctx))
    with pytest.raises(ImssrError, match="no intrinsic signal"):
        _agent(algo="curl").intrinsic_signal(batch, enc)


@pytest.mark.parametrize("algo", ["curl", "im-soda"])
def test_each_backward_computes_only_the_gradients_its_optimisers_step(algo):
    """The actor's loss reads the critic's Q heads for dQ/da: its backward leaves the heads'
    weights alone (a weight gradient nothing steps is work thrown away), so an agent step on
    which critic and actor both train accumulates each Q-head weight's gradient once."""
    from conftest import small_agent

    agent = small_agent(algo, seed=1)
    assert agent.update_key(0)[:2] == (True, True)  # critic and actor both train at step 0
    accumulated = []
    weight = agent.nets.critic.q.q1[0].weight
    weight.register_post_accumulate_grad_hook(lambda p: accumulated.append(1))
    actor_weight = next(agent.nets.actor.parameters())
    actor_weight.register_post_accumulate_grad_hook(lambda p: accumulated.append(2))
    agent.update(filled_buffer(action_dim=2, seed=1, size=60), 0)
    assert accumulated.count(1) == 1 and accumulated.count(2) == 1


def assert_one_pass_is_three(device: str) -> None:
    """The two conversions agree on ``device``, and :func:`pixels` takes the one its device lists."""
    from imssr.networks import encoder

    frames = torch.randint(0, 256, (3, 9, 20, 20), dtype=torch.uint8, generator=torch.Generator().manual_seed(1))
    frames = frames.to(device)
    for dtype in (torch.float32, torch.float64):
        for fmt in (torch.contiguous_format, torch.channels_last):
            for obs in (frames, center_crop(frames, 16)):
                one, three = encoder.one_pass(obs, dtype, fmt), encoder.three_passes(obs, dtype, fmt)
                assert one.dtype == three.dtype == dtype and one.device == obs.device
                assert torch.equal(one, three) and one.stride() == three.stride(), (dtype, fmt)
                assert torch.equal(one, obs.to(dtype) / 255)
    taken = []
    with pytest.MonkeyPatch.context() as mp:
        for name in ("one_pass", "three_passes"):
            mp.setattr(encoder, name, lambda *a, fn=getattr(encoder, name), name=name: taken.append(name) or fn(*a))
        encoder.pixels(frames.clone(), torch.float32, torch.channels_last)
    assert taken == (["one_pass"] if frames.device.type in encoder.ONE_PASS_DEVICES else ["three_passes"])


def test_pixels_in_one_pass_are_the_three_passes_values_and_layout(monkeypatch):
    """CUDA's one-pass conversion gives what the relayout, cast and divide give (a CPU's): the
    same values and strides, in float32 and float64, in both layouts, for contiguous
    frames and a centre crop's view; a device converts in one pass only if it is listed."""
    from imssr.networks import encoder

    assert_one_pass_is_three("cpu")
    monkeypatch.setattr(encoder, "ONE_PASS_DEVICES", {"cpu"})
    assert_one_pass_is_three("cpu")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_pixels_in_one_pass_are_the_three_passes_on_cuda():
    """The same on CUDA, which converts in one pass."""
    assert_one_pass_is_three("cuda")


def test_pixels_convert_each_distinct_input_once():
    """An update passes the same frames through several trunks: the float copy is made once per
    distinct uint8 input (and version of it), with the values of ``obs.float() / 255``, and
    forgotten with its frames."""
    import gc

    from imssr.networks import encoder

    obs = torch.randint(0, 256, (2, 9, 12, 12), dtype=torch.uint8, generator=torch.Generator().manual_seed(0))
    first = encoder.pixels(obs, torch.float32, torch.channels_last)
    assert torch.equal(first, obs.float() / 255) and first.is_contiguous(memory_format=torch.channels_last)
    assert encoder.pixels(obs, torch.float32, torch.channels_last) is first
    assert encoder.pixels(obs, torch.float32, torch.contiguous_format) is not first
    assert encoder.pixels(obs, torch.float32, torch.channels_last, reuse=False) is not first
    obs[0, 0, 0, 0] = 255 - obs[0, 0, 0, 0]  # changed in place: a new version, converted again
    again = encoder.pixels(obs, torch.float32, torch.channels_last)
    assert again is not first and torch.equal(again, obs.float() / 255)
    gc.collect()  # entries of earlier tests' frames that only a collection frees
    entries = len(encoder._PIXELS)
    del obs
    gc.collect()
    assert len(encoder._PIXELS) == entries - 3


@pytest.mark.parametrize("schedule", ["sequential", "fused"])
@pytest.mark.parametrize("algo", ["curl", "im-curl", "soda", "im-soda", "pad", "im-pad", "svea", "im-svea",
                                  "curl+rnd", "soda+re3"])
def test_act_and_update_leave_torchs_global_random_state_untouched(algo, schedule):
    """Every draw of an agent's update and action comes from its own generators: torch's global
    generator, which a batch's members and the rest of the process share, stays as it was."""
    agent = small_agent(algo, schedule)
    replay = filled_buffer(action_dim=2, size=60)
    obs = np.random.default_rng(0).integers(0, 256, (9, 60, 60), dtype=np.uint8)
    before = torch.get_rng_state()
    for step in range(2):  # the actor's and the targets' steps included
        agent.update(replay, step)
        agent.act(obs, deterministic=False)
        agent.act(obs, deterministic=True)
    assert torch.equal(torch.get_rng_state(), before)
