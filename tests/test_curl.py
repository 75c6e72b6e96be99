"""CURL's per-sample InfoNCE loss."""
import torch

from conftest import filled_buffer, tiny_config
from imssr.agents import make_agent
from imssr.auxiliary import AUX_TASKS, AuxiliaryTask
from imssr.batch import NextObsContext


def _agent(seed=0):
    cfg = tiny_config("im-curl")
    return make_agent((9, 100, 100), 1, cfg.agent, cfg.aux, cfg.intrinsic, seed=seed), cfg


def test_per_sample_loss_is_rowwise_cross_entropy_of_logits():
    agent, _ = _agent()
    curl = agent.aux
    torch.manual_seed(0)
    zq, zk = torch.randn(6, 16), torch.randn(6, 16)
    raw = zq @ curl.W @ zk.T
    expected = -(raw.diagonal() - torch.logsumexp(raw, dim=1))
    got = curl.loss_from_latents(zq, zk)
    assert got.shape == (6,)
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)


def test_training_loss_is_mean_of_per_sample_loss():
    agent, _ = _agent()
    batch = agent.to_batch(filled_buffer().sample(8))
    state = agent.gen.get_state()
    per_sample = agent.aux.per_sample_loss(batch)
    agent.gen.set_state(state)  # same positive crops for the update
    metrics = agent.step_aux(batch, step=0)
    assert per_sample.shape == (8,) and per_sample.requires_grad
    torch.testing.assert_close(metrics["aux_loss"], per_sample.mean().detach())


def test_intrinsic_loss_is_per_sample_without_gradients_and_uses_views():
    agent, _ = _agent()
    batch = agent.to_batch(filled_buffer().sample(8))
    n = agent.nets
    enc = agent.encode(batch)
    trunk, target = enc.next_trunk, enc.next_latent  # online trunk and target encoder on o'
    def ctx(form):
        return NextObsContext(batch=batch, enc=enc, generator=torch.Generator().manual_seed(0), form=form)

    shared, indep = agent.aux.intrinsic_loss(ctx("authors")), agent.aux.intrinsic_loss(ctx("training"))
    assert shared.shape == indep.shape == (8,)
    assert not shared.requires_grad and not indep.requires_grad
    # "authors" pairs the online and momentum encoders on the same crop.
    torch.testing.assert_close(shared, agent.aux.loss_from_latents(n.critic.encoder.projection(trunk), target))
    assert not torch.equal(shared, indep)


def test_curl_key_encoder_is_the_critic_target_encoder():
    agent, _ = _agent()
    assert agent.aux.shared.target_encoder is agent.nets.critic_target.encoder
    assert agent.aux.shared.encoder is agent.nets.critic.encoder
    # The shared encoders are the agent's, not registered (and saved) twice.
    assert set(dict(agent.aux.named_parameters())) == {"W"}


def test_registry_holds_curl_and_the_interface_is_abstract():
    assert AUX_TASKS["curl"].name == "curl"
    assert getattr(AuxiliaryTask, "__abstractmethods__") >= {"per_sample_loss", "intrinsic_loss"}
