"""Frame-stacking replay buffer against a naive store of stacked observations."""
import numpy as np
import pytest

from imssr.errors import ImssrError
from imssr.replay import FrameReplayBuffer


class NaiveStore:
    """Keeps every transition's stacked obs and next_obs (what CURL's buffer does)."""

    def __init__(self):
        self.items = []

    def add(self, obs, action, reward, discount, next_obs):
        self.items.append((obs.copy(), np.array(action, np.float32), np.float32(reward),
                           np.float32(discount), next_obs.copy()))


def _stack(frames):
    return np.concatenate(frames, axis=0)


def _fill(capacity, episode_lengths, k=3, size=6, seed=0):
    rng = np.random.default_rng(seed)
    buf = FrameReplayBuffer(capacity, (3, size, size), 2, frame_stack=k, seed=seed)
    naive = NaiveStore()
    for length in episode_lengths:
        frame = rng.integers(0, 256, (3, size, size), dtype=np.uint8)
        buf.add_first(frame)
        stack = [frame] * k
        for _ in range(length):
            a, r = rng.uniform(-1, 1, 2), float(rng.normal())
            d = float(rng.random() < 0.9)
            frame = rng.integers(0, 256, (3, size, size), dtype=np.uint8)
            nxt = stack[1:] + [frame]
            buf.add(a, r, d, frame)
            naive.add(_stack(stack), a, r, d, _stack(nxt))
            stack = nxt
    return buf, naive


def _key(obs, action):
    return obs.tobytes() + action.astype(np.float32).tobytes()


@pytest.mark.parametrize("capacity", [1000, 37])  # no wrap, and a ring that wrapped many times
def test_every_sample_equals_a_naive_transition(capacity):
    lengths = [5, 1, 12, 3, 20, 7, 2, 9]
    buf, naive = _fill(capacity, lengths)
    # The newest transitions, still live in the ring, indexed by (obs, action).
    table = {_key(o, a): (o, a, r, d, n) for o, a, r, d, n in naive.items}
    batch = buf.sample(500)
    for i in range(500):
        o, a, r, d, n = table[_key(batch["obs"][i], batch["action"][i])]
        assert np.array_equal(batch["obs"][i], o)
        assert np.array_equal(batch["next_obs"][i], n)
        assert batch["reward"][i] == r and batch["discount"][i] == d


def test_sampled_set_covers_exactly_the_live_transitions():
    lengths = [4, 6, 3]
    buf, naive = _fill(1000, lengths)
    assert buf.num_transitions() == sum(lengths)
    idx = (buf.head - buf.size + np.arange(buf.size)) % buf.capacity
    valid = idx[buf._valid(idx)]
    got = buf.gather(valid)
    expect = sorted(_key(o, a) for o, a, *_ in naive.items)
    assert sorted(_key(got["obs"][i], got["action"][i]) for i in range(len(valid))) == expect


def test_ring_never_serves_overwritten_history():
    buf, naive = _fill(10, [25], k=3)
    # 10 slots hold the last 10 frames of one episode: 9 transitions, of which
    # the two oldest lack part of their stack.
    assert buf.num_transitions() == 7
    table = {_key(o, a) for o, a, *_ in naive.items[-7:]}
    batch = buf.sample(200)
    assert all(_key(batch["obs"][i], batch["action"][i]) in table for i in range(200))


def test_memory_per_transition_is_one_frame_plus_scalars():
    buf = FrameReplayBuffer(10, (3, 100, 100), 6, warn_memory=False)
    assert buf.bytes_per_slot() <= 30.5 * 1024
    assert buf.nbytes_expected() == sum(a.nbytes for a in (buf.frames, buf.actions, buf.rewards,
                                                            buf.discounts, buf.step_in_episode))
    # 500k transitions of 100x100 frames: about 15 GB.
    assert 500_000 * buf.bytes_per_slot() < 15.5e9


def test_warns_when_memory_is_short(monkeypatch):
    import imssr.replay.buffer as mod

    monkeypatch.setattr(mod, "available_memory_bytes", lambda: 1000)
    with pytest.warns(mod.ReplayMemoryWarning, match="needs"):
        FrameReplayBuffer(100, (3, 10, 10), 1)


def test_save_load_round_trip(tmp_path):
    buf, _ = _fill(37, [5, 12, 30])
    path = str(tmp_path / "replay.npz")
    buf.save(path)
    other = FrameReplayBuffer(37, (3, 6, 6), 2, seed=99)
    other.load(path, buf.state_dict()["rng"])
    a, b = buf.sample(64), other.sample(64)
    for k in a:
        assert np.array_equal(a[k], b[k])


def test_load_errors(tmp_path):
    buf = FrameReplayBuffer(10, (3, 6, 6), 2)
    with pytest.raises(ImssrError, match="not found"):
        buf.load(str(tmp_path / "missing.npz"))
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip file")
    (tmp_path / "bad.npz.frames.npy").write_bytes(b"nor an npy file")
    with pytest.raises(ImssrError, match=r"bad\.npz is not a replay buffer imssr wrote: it carries no imssr checksum$"):
        buf.load(str(bad))
    other, _ = _fill(11, [3])
    other.save(str(tmp_path / "other.npz"))
    with pytest.raises(ImssrError, match="capacity"):
        buf.load(str(tmp_path / "other.npz"))


def test_empty_buffer_refuses_to_sample():
    buf = FrameReplayBuffer(10, (3, 6, 6), 2)
    with pytest.raises(ImssrError, match="no complete transition"):
        buf.sample(4)
    buf.add_first(np.zeros((3, 6, 6), np.uint8))
    with pytest.raises(ImssrError, match="no complete transition"):
        buf.sample(4)


def test_load_into_a_larger_preallocated_ring(tmp_path):
    buf, _ = _fill(5000, [3, 4])  # only a prefix of the ring was ever written
    buf.save(str(tmp_path / "r.npz"))
    other = FrameReplayBuffer(5000, (3, 6, 6), 2)
    other.load(str(tmp_path / "r.npz"))
    assert np.array_equal(other.frames[: buf.head], buf.frames[: buf.head])
