"""The fused update schedule: one encoder pass and one backward for critic + CURL or PAD."""
from dataclasses import replace

import pytest
import torch
import torch.nn.functional as F

from conftest import assert_same_nets, filled_buffer, tiny_config
from imssr.agents import make_agent
from imssr.batch import Encoding, NextObsContext
from imssr.config import apply_overrides
from imssr.errors import ImssrError
from imssr.precision import optimizer_step


def _agent(algo="curl", seed=0, beta0=None, **agent):
    cfg = tiny_config(algo)
    cfg.agent.update_schedule = "fused"
    cfg.aux.own_batch = False  # PAD on the RL batch (DMC-GB's; Table III gives it a batch of its own)
    if beta0 is not None:
        cfg.intrinsic.beta0 = beta0
    for k, v in agent.items():
        setattr(cfg.agent, k, v)
    return make_agent((9, 100, 100), 2, cfg.agent, cfg.aux, cfg.intrinsic, seed=seed)


@pytest.mark.parametrize("algo", ["curl", "pad"])
def test_fused_gradient_is_the_sum_of_the_critic_and_task_gradients(algo):
    agent = _agent(algo)
    n = agent.nets
    batch = agent.to_batch(filled_buffer(action_dim=2).sample(8))
    gen, noise = agent.gen.get_state(), agent.noise_gen.get_state()
    enc, own = list(n.critic.encoder.parameters()), list(agent.aux.parameters())
    # By hand, at the same weights and random draws: each loss's gradient separately.
    with torch.no_grad():
        next_trunk = n.critic.encoder.trunk(batch.next_obs)
        _, a2, logp, _ = n.actor(next_trunk, generator=agent.noise_gen)
        tq = torch.min(*n.critic_target(batch.next_obs, a2)) - agent.alpha * logp
        target = batch.reward + batch.discount * 0.99 * tq
    features = n.critic.encoder.trunk.shared_features(batch.obs)
    trunk = n.critic.encoder.trunk.head(features).flatten(1)
    q1, q2 = n.critic.q(n.critic.encoder.projection(trunk), batch.action)
    critic_loss = F.mse_loss(q1, target) + F.mse_loss(q2, target)
    # PAD runs its own pass over o' here; the agent shares one pass over o and o'.
    next_features = n.critic.encoder.trunk.shared_features(batch.next_obs) if algo == "pad" else None
    by_hand = Encoding(view_weights=(1.0,), features=features, trunk=trunk, next_trunk=next_trunk,
                       next_latent=n.critic_target.encoder(batch.next_obs).detach(), next_features=next_features)
    task_loss = agent.aux.per_sample_loss(batch, by_hand).mean()
    g_critic = torch.autograd.grad(critic_loss, enc, retain_graph=True, allow_unused=True)
    g_task = torch.autograd.grad(task_loss, enc + own, allow_unused=True)
    agent.gen.set_state(gen)
    agent.noise_gen.set_state(noise)
    loss, metrics, obs_trunk = agent.fused_objective(batch, agent.beta(0), with_task_loss=True)
    optimizer_step(loss, agent.critic_opt, agent.aux.optimizer)  # as the fused update steps it
    # The agent's passes run over other batch sizes (o and o' together): rounding differs.
    torch.testing.assert_close(metrics["critic_loss"], critic_loss.detach(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(metrics["aux_loss"], task_loss.detach(), rtol=1e-5, atol=1e-6)
    for p, gc, ga in zip(enc, g_critic, g_task):
        # PAD's loss does not reach the critic's head layers or projection (ga None).
        expected = gc if ga is None else gc + ga
        torch.testing.assert_close(p.grad, expected, rtol=1e-4, atol=1e-6)
    for p, ga in zip(own, g_task[len(enc):]):
        torch.testing.assert_close(p.grad, ga, rtol=1e-4, atol=1e-6)
    # The actor's input is the pre-step encoding, without a graph.
    torch.testing.assert_close(obs_trunk, trunk.detach(), rtol=1e-5, atol=1e-6)
    assert not obs_trunk.requires_grad


@pytest.mark.parametrize("algo", ["curl", "pad"])
def test_fused_task_steps_the_encoder_once_through_the_critic_optimiser(algo):
    agent = _agent(algo)
    aux_params = {id(p) for g in agent.aux.optimizer.param_groups for p in g["params"]}
    assert aux_params == {id(p) for p in agent.aux.parameters()}
    before = [p.clone() for p in agent.nets.critic.encoder.parameters()]
    own_before = [p.clone() for p in agent.aux.parameters()]
    buf = filled_buffer(action_dim=2)
    m = agent.update(buf, 0)
    assert {"critic_loss", "aux_loss", "actor_loss"} <= set(m)
    assert all(not torch.equal(a, b) for a, b in zip(before, agent.nets.critic.encoder.parameters()))
    assert all(not torch.equal(a, b) for a, b in zip(own_before, agent.aux.parameters()))


def test_fused_im_pad_reward_is_the_training_loss_it_reuses():
    """The reused fused loss equals IM-PAD's intrinsic loss computed from scratch."""
    agent = _agent("im-pad")
    batch = agent.to_batch(filled_buffer(action_dim=2).sample(8))
    fused = agent.encode(batch, with_task_loss=True).aux_loss
    ctx = NextObsContext(batch=batch, enc=None, generator=agent.intrinsic_gen)
    torch.testing.assert_close(agent.aux.intrinsic_loss(ctx), fused.detach(), rtol=1e-5, atol=1e-6)


def test_fused_im_pad_update_hands_its_training_loss_to_the_reward():
    agent = _agent("im-pad")
    seen = []
    compute = agent.aux.intrinsic_loss

    def spy(ctx):  # records what the agent passes and what the task returns from it
        handed = ctx.enc.aux_loss
        got = compute(ctx)
        seen.append((handed, got, compute(replace(ctx, enc=replace(ctx.enc, aux_loss=None)))))
        return got

    agent.signal.task_loss = spy
    batch = agent.to_batch(filled_buffer(action_dim=2).sample(8))
    metrics = agent.fused_objective(batch, agent.beta(0), with_task_loss=True)[1]
    ((handed, got, recomputed),) = seen
    assert handed is not None and not got.requires_grad
    torch.testing.assert_close(got, handed.detach())
    torch.testing.assert_close(got, recomputed, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(metrics["aux_loss"], got.mean())
    # Sequential schedule: nothing to hand over, the reward computes the loss itself.
    seen.clear()
    batch = agent.to_batch(filled_buffer(action_dim=2).sample(8))
    agent.critic_objective(batch, agent.beta(1))
    assert seen[0][0] is None


@pytest.mark.parametrize("algo", ["curl", "soda", "pad", "svea"])
def test_every_base_trains_under_the_fused_schedule(algo):
    agent = _agent(algo)
    buf = filled_buffer(action_dim=2)
    for s in range(3):
        m = agent.update(buf, s)
        assert torch.isfinite(torch.as_tensor(float(m["critic_loss"])))


@pytest.mark.parametrize("base_algo", ["curl", "pad"])
def test_fused_beta_zero_is_the_baseline_and_round_trip_continues_identically(base_algo):
    buf_a, buf_b = filled_buffer(action_dim=2, seed=1), filled_buffer(action_dim=2, seed=1)
    base, im0 = _agent(base_algo), _agent(f"im-{base_algo}", beta0=0.0)
    for s in range(3):
        base.update(buf_a, s)
        assert "r_int_mean" in im0.update(buf_b, s)
    assert_same_nets(base, im0)
    clone = _agent(base_algo, seed=7)
    clone.load_state_dict(base.state_dict())
    buf_c = filled_buffer(action_dim=2, seed=1)
    buf_c.rng.bit_generator.state = buf_a.rng.bit_generator.state
    for s in range(3, 5):
        base.update(buf_a, s)
        clone.update(buf_c, s)
    assert_same_nets(base, clone)


def test_schedule_is_validated():
    cfg = tiny_config("curl")
    with pytest.raises(ImssrError, match="update_schedule"):
        apply_overrides(cfg, ["agent.update_schedule=joint"]).validate()
    with pytest.raises(ImssrError, match="critic_update_every"):
        apply_overrides(tiny_config("curl"), ["agent.update_schedule=fused",
                                              "agent.critic_update_every=2"]).validate()


def test_pad_on_its_own_batch_is_not_fused_and_still_trains_the_shared_layers():
    cfg = tiny_config("pad")
    cfg.agent.update_schedule = "fused"
    assert cfg.aux.own_batch  # Table III: PAD's SSL batch is its own (256)
    agent = make_agent((9, 100, 100), 2, cfg.agent, cfg.aux, cfg.intrinsic, seed=0)
    assert not agent.fuse_aux
    convs = agent.nets.critic.encoder.trunk.convs
    owned = {id(p) for g in agent.aux.optimizer.param_groups for p in g["params"]}
    assert all(id(p) in owned for p in convs.parameters())
    before = [p.clone() for p in convs.parameters()]
    agent.step_aux(agent.to_batch(filled_buffer(action_dim=2).sample(8)), 0)
    assert any(not torch.equal(a, b) for a, b in zip(before, convs.parameters()))
