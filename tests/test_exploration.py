"""RND and RE3: the exploration peers that swap only the intrinsic signal."""
import numpy as np
import pytest
import torch

from conftest import filled_buffer, tiny_config
from imssr.agents import make_agent
from imssr.batch import NextObsContext
from imssr.intrinsic import RE3, RND


def _agent(algo):
    cfg = tiny_config(algo)
    return make_agent((9, 100, 100), 2, cfg.agent, cfg.aux, cfg.intrinsic, seed=0), cfg


def _ctx(batch):
    return NextObsContext(batch=batch, enc=None, generator=torch.Generator(), form="independent")


def test_one_setting_swaps_the_signal():
    for algo, kind in (("curl+rnd", RND), ("soda+re3", RE3)):
        agent, cfg = _agent(algo)
        assert isinstance(agent.signal, kind) and cfg.aux.name == algo.split("+")[0]
        base = tiny_config(f"im-{cfg.aux.name}").intrinsic
        # Same beta_0, schedule and normalisation as the IM- variant of the base.
        assert (cfg.intrinsic.beta0, cfg.intrinsic.schedule, cfg.intrinsic.normalization) == \
            (base.beta0, base.schedule, base.normalization)


def test_rnd_error_is_per_sample_and_falls_on_seen_observations():
    agent, _ = _agent("curl+rnd")
    rnd = agent.signal
    batch = agent.to_batch(filled_buffer(action_dim=2).sample(8))
    err = rnd(_ctx(batch))
    assert err.shape == (8,) and not err.requires_grad and torch.all(err >= 0)
    target_before = [p.clone() for p in rnd.target.parameters()]
    for _ in range(30):
        agent.update_signal(batch)
    assert float(rnd(_ctx(batch)).mean()) < 0.5 * float(err.mean())
    # The target network is fixed.
    assert all(torch.equal(a, b) for a, b in zip(target_before, rnd.target.parameters()))
    # Unseen observations keep a higher error than the ones trained on.
    other = agent.to_batch(filled_buffer(action_dim=2, seed=9).sample(8))
    assert float(rnd(_ctx(other)).mean()) > float(rnd(_ctx(batch)).mean())


def test_re3_is_the_log_kth_neighbour_distance_in_a_fixed_random_space():
    agent, cfg = _agent("curl+re3")
    re3 = agent.signal
    batch = agent.to_batch(filled_buffer(action_dim=2).sample(8))
    got = re3(_ctx(batch))
    y = re3.encoder(batch.next_obs).detach().numpy().astype(np.float64)
    d = np.linalg.norm(y[:, None] - y[None], axis=-1)
    expected = np.log1p(np.sort(d, axis=1)[:, cfg.intrinsic.re3_k])
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-4, atol=1e-5)
    assert not any(p.requires_grad for p in re3.parameters())
    # k + 1 copies of each observation: every k-th neighbour is a copy, distance 0.
    k = cfg.intrinsic.re3_k
    dup = batch.next_obs[:2].repeat_interleave(k + 1, dim=0)
    b2 = agent.to_batch(filled_buffer(action_dim=2).sample(2 * (k + 1)))
    b2.next_obs = dup
    assert torch.allclose(re3(_ctx(b2)), torch.zeros(2 * (k + 1)), atol=1e-5)


@pytest.mark.parametrize("algo", ["curl+rnd", "svea+re3"])
def test_peer_state_round_trip(algo):
    agent, cfg = _agent(algo)
    buf = filled_buffer(action_dim=2)
    for s in range(2):
        agent.update(buf, s)
    other = make_agent((9, 100, 100), 2, cfg.agent, cfg.aux, cfg.intrinsic, seed=4)
    other.load_state_dict(agent.state_dict())
    for (k, v), (_, w) in zip(agent.signal.state_dict().items(), other.signal.state_dict().items()):
        assert torch.equal(v, w), k
