"""The fused update schedule: one encoder pass and one backward for critic + CURL."""
import pytest
import torch
import torch.nn.functional as F

from conftest import assert_same_nets, filled_buffer, tiny_config
from imssr.agents import SACAgent
from imssr.config import apply_overrides
from imssr.errors import ImssrError


def _agent(algo="curl", seed=0, beta0=None, **agent):
    cfg = tiny_config(algo)
    cfg.agent.update_schedule = "fused"
    if beta0 is not None:
        cfg.intrinsic.beta0 = beta0
    for k, v in agent.items():
        setattr(cfg.agent, k, v)
    return SACAgent((9, 100, 100), 2, cfg.agent, cfg.aux, cfg.intrinsic, seed=seed)


def test_fused_gradient_is_the_sum_of_the_critic_and_curl_gradients():
    agent = _agent()
    n = agent.nets
    batch = agent.to_batch(filled_buffer(action_dim=2).sample(8))
    gen, noise = agent.gen.get_state(), agent.noise_gen.get_state()
    enc = list(n.critic.encoder.parameters())
    # By hand, at the same weights and random draws: each loss's gradient separately.
    with torch.no_grad():
        _, a2, logp, _ = n.actor(n.critic.encoder.trunk(batch.next_obs), generator=agent.noise_gen)
        tq = torch.min(*n.critic_target(batch.next_obs, a2)) - agent.alpha * logp
        target = batch.reward + batch.discount * 0.99 * tq
    trunk = n.critic.encoder.trunk(batch.obs)
    q1, q2 = n.critic.q(n.critic.encoder.projection(trunk), batch.action)
    critic_loss = F.mse_loss(q1, target) + F.mse_loss(q2, target)
    curl_loss = agent.aux.loss_from_trunk(batch, trunk).mean()
    g_critic = torch.autograd.grad(critic_loss, enc, retain_graph=True)
    g_curl = torch.autograd.grad(curl_loss, enc + [agent.aux.W])
    agent.gen.set_state(gen)
    agent.noise_gen.set_state(noise)
    metrics, obs_trunk = agent.update_critic(batch, 0, fuse_aux=True)
    torch.testing.assert_close(metrics["critic_loss"], critic_loss.detach())
    torch.testing.assert_close(metrics["aux_loss"], curl_loss.detach())
    for p, gc, ga in zip(enc, g_critic, g_curl):
        torch.testing.assert_close(p.grad, gc + ga, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(agent.aux.W.grad, g_curl[-1])
    # The actor's input is the pre-step encoding, without a graph.
    torch.testing.assert_close(obs_trunk, trunk.detach())
    assert not obs_trunk.requires_grad


def test_fused_curl_steps_the_encoder_once_through_the_critic_optimiser():
    agent = _agent()
    aux_params = {id(p) for g in agent.aux.optimizer.param_groups for p in g["params"]}
    assert aux_params == {id(agent.aux.W)}
    before = [p.clone() for p in agent.nets.critic.encoder.parameters()]
    w_before = agent.aux.W.clone()
    buf = filled_buffer(action_dim=2)
    m = agent.update(buf, 0)
    assert {"critic_loss", "aux_loss", "actor_loss"} <= set(m)
    assert all(not torch.equal(a, b) for a, b in zip(before, agent.nets.critic.encoder.parameters()))
    assert not torch.equal(w_before, agent.aux.W)


@pytest.mark.parametrize("algo", ["curl", "soda", "pad", "svea"])
def test_every_base_trains_under_the_fused_schedule(algo):
    agent = _agent(algo)
    buf = filled_buffer(action_dim=2)
    for s in range(3):
        m = agent.update(buf, s)
        assert torch.isfinite(torch.as_tensor(float(m["critic_loss"])))


def test_fused_beta_zero_is_the_baseline_and_round_trip_continues_identically():
    buf_a, buf_b = filled_buffer(action_dim=2, seed=1), filled_buffer(action_dim=2, seed=1)
    base, im0 = _agent("curl"), _agent("im-curl", beta0=0.0)
    for s in range(3):
        base.update(buf_a, s)
        assert "r_int_mean" in im0.update(buf_b, s)
    assert_same_nets(base, im0)
    clone = _agent("curl", seed=7)
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
