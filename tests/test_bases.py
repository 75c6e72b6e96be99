"""SODA, PAD and SVEA: per-sample losses and how each plugs into the agent."""
import math
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from conftest import filled_buffer, next_obs_context, tiny_config
from imssr.agents import make_agent
from imssr.augmentations import center_crop


def _agent(algo, seed=0, action_dim=2):
    cfg = tiny_config(algo)
    return make_agent((9, 100, 100), action_dim, cfg.agent, cfg.aux, cfg.intrinsic, seed=seed)


@pytest.mark.parametrize("algo", ["soda", "pad"])
def test_training_loss_is_the_mean_of_the_per_sample_loss(algo):
    agent = _agent(algo)
    batch = agent.to_batch(filled_buffer(action_dim=2).sample(8))
    state = agent.gen.get_state()
    per_sample = agent.aux.per_sample_loss(batch)
    agent.gen.set_state(state)  # the same overlay images for the update
    metrics = agent.step_aux(batch, step=0)
    assert per_sample.shape == (8,) and per_sample.requires_grad
    torch.testing.assert_close(metrics["aux_loss"], per_sample.mean().detach())


def test_soda_loss_is_the_normalised_l2_of_predictor_and_target():
    agent = _agent("soda")
    soda = agent.aux
    batch = agent.to_batch(filled_buffer(action_dim=2).sample(8))
    aug = soda.overlay(batch.obs, torch.Generator().manual_seed(0))
    got = soda.squared_distance(aug, batch.obs).mean(dim=1)
    h = soda.predictor(soda.projection(agent.nets.critic.encoder.trunk(aug)))
    t = soda.target_projection(soda.target_trunk(batch.obs))
    cos = F.cosine_similarity(h, t, dim=1)
    # ||a/|a| - b/|b|||^2 = 2 - 2 cos(a, b), averaged over the latent dimensions.
    torch.testing.assert_close(got, (2 - 2 * cos) / h.shape[1], rtol=1e-4, atol=1e-6)
    # DMC-GB's reduction: F.mse_loss of the normalised vectors.
    torch.testing.assert_close(got.mean(), F.mse_loss(F.normalize(h), F.normalize(t)), rtol=1e-5, atol=1e-7)


def test_soda_trains_on_its_own_batch_and_moves_its_target_slowly():
    agent = _agent("soda")
    soda = agent.aux
    assert soda.cfg.own_batch and soda.cfg.batch_size == 8
    before = [p.clone() for p in soda.target_trunk.parameters()]
    buf = filled_buffer(action_dim=2)
    m0 = agent.update(buf, 0)
    # After one aux step the target moved by exactly tau towards the online weights.
    for p0, p, q in zip(before, soda.target_trunk.parameters(), agent.nets.critic.encoder.trunk.parameters()):
        torch.testing.assert_close(p, torch.lerp(p0, q, 0.005), rtol=0, atol=1e-7)
    m1 = agent.update(buf, 1)
    assert "aux_loss" in m0 and "aux_loss" not in m1  # every 2 steps


def test_soda_intrinsic_loss_is_per_sample_and_gradient_free():
    agent = _agent("im-soda")
    batch = agent.to_batch(filled_buffer(action_dim=2).sample(8))
    loss = agent.aux.intrinsic_loss(next_obs_context(agent, batch))
    # The authors' form: log(1 + sum of squares of two unit vectors' difference), in [0, log 5].
    assert loss.shape == (8,) and not loss.requires_grad and torch.all(loss >= 0)
    assert torch.all(loss <= math.log(5.0) + 1e-6)


def test_pad_shares_only_the_first_layers_and_predicts_actions():
    cfg = tiny_config("pad")
    assert (cfg.agent.encoder_layers, cfg.agent.encoder_head_layers) == (11, 3)
    agent = _agent("pad")
    pad, trunk = agent.aux, agent.nets.critic.encoder.trunk
    trained = {id(p) for g in pad.optimizer.param_groups for p in g["params"]}
    assert {id(p) for p in trunk.convs.parameters()} <= trained
    assert not {id(p) for p in trunk.head.parameters()} & trained
    assert len(pad.head) == 2 * 3  # its own 3 head layers (conv + ReLU)
    batch = agent.to_batch(filled_buffer(action_dim=2).sample(8))
    pred = pad.predict_action(batch.obs, batch.next_obs)
    assert pred.shape == (8, 2)
    torch.testing.assert_close(pad.per_sample_loss(batch), (pred - batch.action).pow(2).mean(1))


def test_pad_learns_the_inverse_dynamics_of_a_fixed_batch():
    agent = _agent("pad")
    batch = agent.to_batch(filled_buffer(action_dim=2).sample(8))
    first = float(agent.step_aux(batch, 0)["aux_loss"])
    for s in range(1, 40):
        last = float(agent.step_aux(batch, s)["aux_loss"])
    assert last < 0.5 * first


def test_pad_intrinsic_loss_is_the_inverse_dynamics_error_of_the_transition():
    agent = _agent("im-pad")
    batch = agent.to_batch(filled_buffer(action_dim=2).sample(8))
    got = agent.aux.intrinsic_loss(next_obs_context(agent, batch))
    with torch.no_grad():
        expected = agent.aux.per_sample_loss(batch)
    assert not got.requires_grad
    torch.testing.assert_close(got, expected)


def test_svea_critic_views_and_loss_weights():
    agent = _agent("svea")
    batch = agent.to_batch(filled_buffer(action_dim=2).sample(8))
    views = agent.aux.critic_views(batch)
    assert [w for _, w in views] == [0.5, 0.5]
    assert torch.equal(views[0][0], batch.obs)
    aug = views[1][0]
    assert aug.shape == batch.obs.shape and not torch.equal(aug.float(), batch.obs.float())
    assert not agent.aux.trains and agent.aux.optimizer is None
    m = agent.update(filled_buffer(action_dim=2), 0)
    assert "aux_loss" not in m and np.isfinite(float(m["critic_loss"]))


def test_svea_critic_loss_matches_the_weighted_sum():
    """alpha * L(clean) + beta * L(aug), both to the clean target (paper, Eq. L_SVEA)."""
    agent = _agent("svea")
    agent.aux.cfg.svea_alpha, agent.aux.cfg.svea_beta = 0.25, 2.0
    batch = agent.to_batch(filled_buffer(action_dim=2).sample(8))
    gen_state = agent.gen.get_state()
    views = agent.aux.critic_views(batch)
    agent.gen.set_state(gen_state)
    noise_state = agent.noise_gen.get_state()
    n = agent.nets
    with torch.no_grad():
        _, a2, logp, _ = n.actor(n.critic.encoder.trunk(batch.next_obs), generator=agent.noise_gen)
        tq = torch.min(*n.critic_target(batch.next_obs, a2)) - agent.alpha * logp
        target = batch.reward + batch.discount * 0.99 * tq
        expected = sum(w * sum(F.mse_loss(q, target) for q in n.critic(v, batch.action)) for v, w in views)
    agent.noise_gen.set_state(noise_state)
    got = agent.critic_objective(batch, agent.beta(0))[1]["critic_loss"]
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-6)


def test_im_svea_signal_is_zero_when_online_equals_target():
    agent = _agent("im-svea")
    batch = agent.to_batch(filled_buffer(action_dim=2).sample(8))
    # At initialisation the target encoder is an exact copy: nothing to explain yet.
    assert torch.all(agent.aux.intrinsic_loss(next_obs_context(agent, batch)) == 0)
    with torch.no_grad():
        for p in agent.nets.critic.encoder.projection.parameters():
            p.add_(0.1 * torch.randn_like(p))
    loss = agent.aux.intrinsic_loss(next_obs_context(agent, batch))
    z_hat = agent.nets.critic.encoder(batch.next_obs)
    z_star = agent.nets.critic_target.encoder(batch.next_obs)
    torch.testing.assert_close(loss, (z_hat - z_star).pow(2).sum(1).detach(), rtol=1e-4, atol=1e-6)
    assert torch.all(loss > 0)


def test_dmcgb_encoders_use_tanh_projections():
    agent = _agent("soda")
    z = agent.nets.critic.encoder(center_crop(torch.randint(0, 256, (4, 9, 100, 100), dtype=torch.uint8), agent.cfg.crop_size))
    assert z.shape == (4, 16) and float(z.detach().abs().max()) <= 1.0
