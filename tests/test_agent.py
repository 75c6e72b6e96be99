"""SAC agent: actions, determinism, save/load round trip, update schedule."""
import numpy as np

from conftest import assert_same_nets, filled_buffer, tiny_config
from imssr.agents import SACAgent


def _agent(seed=0, algo="curl"):
    cfg = tiny_config(algo)
    return SACAgent((9, 100, 100), 2, cfg.agent, cfg.aux, cfg.intrinsic, seed=seed)


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
