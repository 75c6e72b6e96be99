"""The two frame stores: the numpy host store and the tensor store (run here on the CPU) draw the
same indices, give the same batches and write the same files, so either resumes the other."""
import numpy as np
import pytest
import torch

import imssr.replay.buffer as buffer_module
import imssr.replay.device as device_module
from imssr.replay import FrameReplayBuffer, TensorFrameReplayBuffer
from imssr.replay.buffer import Packing, ReplayFileError, frames_path

SHAPE = (3, 6, 6)


def _fill(buf, n_steps=300, episode_len=37, seed=0):
    """Random frames and fields in episodes of ``episode_len`` transitions, some terminal."""
    rng = np.random.default_rng(seed)
    for t in range(n_steps):
        if t % episode_len == 0:
            buf.add_first(rng.integers(0, 256, SHAPE, dtype=np.uint8), rng.normal(size=buf.physics_dim), t)
        buf.add(rng.uniform(-1, 1, buf.action_dim), float(rng.normal()), float(rng.random() < 0.9),
                rng.integers(0, 256, SHAPE, dtype=np.uint8), rng.normal(size=buf.physics_dim), t + 1)
    return buf


def _host(capacity=100, seed=5, **kw):
    return FrameReplayBuffer(capacity, SHAPE, 2, seed=seed, **kw)


def _tensor(capacity=100, seed=5, **kw):
    return TensorFrameReplayBuffer(capacity, SHAPE, 2, seed=seed, device="cpu", **kw)


def _assert_same_batch(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(torch.as_tensor(a[k]), torch.as_tensor(b[k])), k


def _frames(buf) -> np.ndarray:
    return np.asarray(buf.frames[:buf.size])


@pytest.mark.parametrize("capacity", [1000, 100])  # no wrap, and a ring that wrapped
def test_the_tensor_store_gives_the_host_stores_batches(capacity):
    host, tensor = _fill(_host(capacity)), _fill(_tensor(capacity))
    assert isinstance(tensor.frames, torch.Tensor) and tensor.frames.dtype == torch.uint8
    for batch_size in (64, 7, 128):
        _assert_same_batch(host.sample_batch(batch_size, "cpu"), tensor.sample_batch(batch_size, "cpu"))
    assert host.rng.bit_generator.state == tensor.rng.bit_generator.state
    _assert_same_batch(host.sample(32), tensor.sample(32))  # the numpy interface too


def test_sample_batch_is_sample_as_tensors():
    """The tensors an update gets are what ``torch.as_tensor`` made of :meth:`sample`'s arrays:
    the same draws, values, dtypes and strides."""
    a, b = _fill(_host()), _fill(_host())
    for _ in range(3):
        tensors, arrays = a.sample_batch(64, torch.device("cpu")), b.sample(64)
        for k, array in arrays.items():
            expected = torch.as_tensor(array)
            assert tensors[k].dtype == expected.dtype and tensors[k].stride() == expected.stride(), k
            assert torch.equal(tensors[k], expected), k
    assert a.rng.bit_generator.state == b.rng.bit_generator.state


def test_the_packed_staging_buffer_round_trips():
    packing = Packing([(torch.uint8, (5, 3)), (torch.int64, (4,)), (torch.float32, (3, 2)), (torch.float32, (3,))])
    assert all(offset % 8 == 0 for offset in packing.offsets) and packing.nbytes % 8 == 0
    host = packing.host_buffer(pin=False)
    values = [torch.arange(15, dtype=torch.uint8).view(5, 3), torch.tensor([1, -2, 3, 2**40]),
              torch.rand(3, 2), torch.rand(3)]
    for view, value in zip(packing.views(host), values):
        view.copy_(value)
    for view, value in zip(packing.views(host.clone()), values):  # as after the copy to a device
        assert view.dtype == value.dtype and torch.equal(view, value)


@pytest.mark.parametrize("capacity", [1000, 100])
def test_both_stores_write_the_same_files(tmp_path, capacity, chunks):
    host, tensor = _fill(_host(capacity, physics_dim=4)), _fill(_tensor(capacity, physics_dim=4))
    a, b = str(tmp_path / "host.npz"), str(tmp_path / "tensor.npz")
    host.save(a)
    tensor.save(b)
    with open(frames_path(a), "rb") as fa, open(frames_path(b), "rb") as fb:
        assert fa.read() == fb.read()
    with np.load(a) as da, np.load(b) as db:
        assert da.files == db.files
        for k in da.files:
            assert np.array_equal(da[k], db[k]), k
    assert np.array_equal(np.load(frames_path(b)), _frames(host)[:capacity])


@pytest.fixture(params=["one chunk", "many chunks"])
def chunks(request, monkeypatch):
    """Frames copied and read in one chunk (a small buffer), or in chunks of 250 bytes, not a
    whole number of frames (what a large buffer does)."""
    if request.param == "many chunks":
        for module in (device_module, buffer_module):
            monkeypatch.setattr(module, "READ_CHUNK", 250)
        monkeypatch.setattr(device_module, "SAVE_CHUNK", 250)


@pytest.mark.parametrize("writer, reader", [(_host, _tensor), (_tensor, _host), (_tensor, _tensor)])
def test_a_file_of_one_store_resumes_in_the_other(tmp_path, writer, reader, chunks):
    saved = _fill(writer(physics_dim=4))
    saved.sample_batch(16, "cpu")  # the sampler has moved on: its state goes with the checkpoint
    path = str(tmp_path / "replay.npz")
    saved.save(path)
    loaded = reader(seed=99, physics_dim=4)
    loaded.load(path, saved.state_dict()["rng"])
    assert loaded.state_dict() == saved.state_dict()
    assert np.array_equal(_frames(loaded), _frames(saved))
    assert np.array_equal(loaded.physics, saved.physics) and np.array_equal(loaded.agent_step, saved.agent_step)
    for _ in range(3):
        _assert_same_batch(loaded.sample_batch(32, "cpu"), saved.sample_batch(32, "cpu"))
    # Both go on writing the same ring.
    _fill(saved, n_steps=50, seed=1)
    _fill(loaded, n_steps=50, seed=1)
    _assert_same_batch(loaded.sample_batch(32, "cpu"), saved.sample_batch(32, "cpu"))


def test_the_tensor_store_verifies_what_it_loads(tmp_path):
    path = str(tmp_path / "replay.npz")
    _fill(_host()).save(path)
    with open(frames_path(path), "r+b") as fh:
        fh.seek(-1, 2)
        last = fh.read(1)
        fh.seek(-1, 2)
        fh.write(bytes([last[0] ^ 0xFF]))
    with pytest.raises(ReplayFileError, match=r"replay\.npz\.frames\.npy is damaged \(checksum mismatch\)"):
        _tensor().load(path)
    with open(frames_path(path), "r+b") as fh:
        fh.truncate(200)
    with pytest.raises(ReplayFileError, match="truncated"):
        _tensor().load(path)


def test_an_empty_tensor_store_saves_and_loads(tmp_path):
    path = str(tmp_path / "replay.npz")
    _tensor().save(path)
    other = _tensor()
    other.load(path)
    assert len(other) == 0 and np.load(frames_path(path)).shape == (0, *SHAPE)


def test_the_tensor_store_takes_any_frame_layout():
    """Frames are copied in as uint8, whatever the strides of the array they come in."""
    buf = _tensor()
    frame = np.arange(3 * 6 * 6, dtype=np.uint8).reshape(6, 6, 3).transpose(2, 0, 1)[:, ::-1]
    buf.add_first(frame)
    assert np.array_equal(buf.frames[0].numpy(), frame)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_on_a_gpu_both_paths_give_the_cpu_batches(tmp_path):
    reference = _fill(_host())
    host = _fill(_host())
    device = _fill(TensorFrameReplayBuffer(100, SHAPE, 2, seed=5, device="cuda"))
    for _ in range(3):
        expected = reference.sample_batch(64, "cpu")
        for got in (host.sample_batch(64, "cuda"), device.sample_batch(64, "cuda")):
            assert all(v.device.type == "cuda" for v in got.values())
            _assert_same_batch({k: v.cpu() for k, v in got.items()}, expected)
    path = str(tmp_path / "replay.npz")
    device.save(path)
    loaded = _host()
    loaded.load(path, device.state_dict()["rng"])
    assert np.array_equal(_frames(loaded), device.frames[:device.size].cpu().numpy())
