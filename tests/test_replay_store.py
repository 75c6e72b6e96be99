"""The two frame stores: the numpy host store and the tensor store (run here on the CPU) draw the
same indices, give the same batches and write the same files, so either resumes the other."""
import os
import re

import numpy as np
import pytest
import torch

from conftest import as_single_file_replay
import imssr.replay.buffer as buffer_module
import imssr.replay.device as device_module
from imssr.integrity import seal_zip
from imssr.replay import FrameReplayBuffer, TensorFrameReplayBuffer
from imssr.replay.buffer import Packing, ReplayFileError, replay_files

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
    a, b = str(tmp_path / "host" / "replay.npz"), str(tmp_path / "tensor" / "replay.npz")
    host.save(a)
    tensor.save(b)
    files_a, files_b = replay_files(a), replay_files(b)
    assert [os.path.basename(f) for f in files_a] == [os.path.basename(f) for f in files_b]
    for fa, fb in zip(files_a, files_b):
        with open(fa, "rb") as ha, open(fb, "rb") as hb:
            assert ha.read() == hb.read(), fa
    # The frame file holds the live frames in the order they were written.
    (frame_file,) = files_b[1:]
    order = np.arange(host.written - host.size, host.written) % capacity
    assert np.array_equal(np.load(frame_file), np.asarray(host.frames)[order])


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
    frame_file = replay_files(path)[-1]
    with open(frame_file, "r+b") as fh:
        fh.seek(-1, 2)
        last = fh.read(1)
        fh.seek(-1, 2)
        fh.write(bytes([last[0] ^ 0xFF]))
    with pytest.raises(ReplayFileError, match=r"replay-frames-\d+-\d+\.npy is damaged \(checksum mismatch\)"):
        _tensor().load(path)
    with open(frame_file, "r+b") as fh:
        fh.truncate(200)
    with pytest.raises(ReplayFileError, match="truncated"):
        _tensor().load(path)


def test_an_empty_tensor_store_saves_and_loads(tmp_path):
    path = str(tmp_path / "replay.npz")
    _tensor().save(path)
    other = _tensor()
    other.load(path)
    assert len(other) == 0 and replay_files(path) == [path]


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


# -- saves that write only what is new ------------------------------------------------------

def _frame_files(directory) -> dict[str, tuple[int, int]]:
    """The frame files in ``directory`` and their (inode, mtime): which writes made them."""
    return {f: (os.stat(os.path.join(directory, f)).st_ino, os.stat(os.path.join(directory, f)).st_mtime_ns)
            for f in os.listdir(directory) if f.startswith("replay-frames-")}


def test_a_save_writes_only_the_frames_since_the_last_one(tmp_path):
    buf = _fill(_host(capacity=1000), n_steps=100)
    buf.save(str(tmp_path / "a.npz"))
    first = _frame_files(tmp_path)
    _fill(buf, n_steps=50, seed=1)
    buf.save(str(tmp_path / "b.npz"))
    files = replay_files(str(tmp_path / "b.npz"))
    # The first file is the one written before (same inode and time), named again; the new one
    # holds the 52 frames written since (50 transitions and two episodes' first frames).
    assert {f: v for f, v in _frame_files(tmp_path).items() if f in first} == first
    assert [os.path.basename(f) for f in files[1:]] == [*first, "replay-frames-000000000103-000000000155.npy"]
    assert np.load(files[2]).shape == (52, *SHAPE)
    buf.save(str(tmp_path / "c.npz"))  # nothing new: no frame file written
    assert replay_files(str(tmp_path / "c.npz"))[1:] == files[1:] and len(_frame_files(tmp_path)) == 2


@pytest.mark.parametrize("store", [_host, _tensor])
@pytest.mark.parametrize("every", [7, 33, 150])  # 150 > capacity: more than a ring between saves
def test_saves_across_the_rings_wraps_load_exactly(tmp_path, store, every, chunks):
    buf, rng = store(capacity=100), np.random.default_rng(3)
    for save in range(8):
        _fill(buf, n_steps=every, episode_len=int(rng.integers(5, 40)), seed=save)
        path = str(tmp_path / f"replay-{save}.npz")
        buf.save(path)
        loaded = store(capacity=100, seed=99)
        loaded.load(path, buf.state_dict()["rng"])
        assert loaded.state_dict() == buf.state_dict() and loaded.written == buf.written
        live = buf.live_slots()
        assert np.array_equal(np.asarray(loaded.frames)[live], np.asarray(buf.frames)[live])
        _assert_same_batch(loaded.sample_batch(32, "cpu"), buf.sample_batch(32, "cpu"))
        # Only files that still hold a live frame are named.
        assert all(int(f[-16:-4]) > buf.written - buf.size for f in replay_files(path)[1:])


def test_a_missing_frame_file_is_one_line_and_the_next_save_writes_them_all(tmp_path):
    buf = _fill(_host(capacity=1000), n_steps=60)
    buf.save(str(tmp_path / "a.npz"))
    _fill(buf, n_steps=60, seed=1)
    buf.save(str(tmp_path / "b.npz"))
    lost = replay_files(str(tmp_path / "b.npz"))[1]
    os.unlink(lost)
    with pytest.raises(ReplayFileError, match=rf"^replay buffer file not found: {lost}$"):
        _host(capacity=1000).load(str(tmp_path / "b.npz"))
    buf.save(str(tmp_path / "c.npz"))
    (whole,) = replay_files(str(tmp_path / "c.npz"))[1:]
    assert np.load(whole).shape == (buf.size, *SHAPE)
    _host(capacity=1000).load(str(tmp_path / "c.npz"))


def test_an_index_that_misses_frames_is_refused(tmp_path):
    buf = _fill(_host(capacity=1000), n_steps=60)
    buf.save(str(tmp_path / "a.npz"))
    _fill(buf, n_steps=60, seed=1)
    path = str(tmp_path / "b.npz")
    buf.save(path)
    with np.load(path) as data:
        fields = {k: data[k] for k in data.files}
    fields["frame_chunks"], fields["frame_chunk_sha256"] = fields["frame_chunks"][1:], fields["frame_chunk_sha256"][1:]
    with open(path, "wb") as fh:
        np.savez(fh, **fields)
    seal_zip(path)  # a sealed index that lists too little: what the frame list itself must catch
    with pytest.raises(ReplayFileError, match=r"b\.npz does not name frame files for all its frames$"):
        _host(capacity=1000).load(path)


def _empty(path):
    open(path, "wb").close()


def _bad_magic(path):
    with open(path, "r+b") as fh:
        fh.write(b"XNUMPY")


def _bad_header(path):
    data = open(path, "rb").read()
    with open(path, "wb") as fh:
        fh.write(data.replace(b"'descr'", b"'dexcr'", 1))


@pytest.mark.parametrize("fault, what", [(_empty, "empty"),
                                         (_bad_magic, "its .npy header is unreadable: "),
                                         (_bad_header, "its .npy header is unreadable: ")])
def test_a_frame_file_with_a_damaged_header_is_named(tmp_path, fault, what):
    """The index is whole and verified: the frame file is what is damaged, and the line says so."""
    path = str(tmp_path / "replay.npz")
    _fill(_host()).save(path)
    frame_file = replay_files(path)[-1]
    fault(frame_file)
    with pytest.raises(ReplayFileError, match=rf"^replay frames {re.escape(frame_file)} are damaged "
                                              rf"\({re.escape(what)}"):
        _host().load(path)


def _cut_last_byte(path):
    data = open(path, "rb").read()
    with open(path, "wb") as fh:
        fh.write(data[:-1])


def _unsealed(path):
    with np.load(path) as data:
        fields = {k: data[k] for k in data.files}
    with open(path, "wb") as fh:
        np.savez(fh, **fields)


@pytest.mark.parametrize("fault, message", [
    (_cut_last_byte, "replay buffer {} is damaged (its checksum is not at its end: cut short or extended)"),
    (_unsealed, "{} is not a replay buffer imssr wrote: it carries no imssr checksum")])
def test_an_index_that_cannot_be_verified_is_refused(tmp_path, fault, message):
    """numpy reads both files as they are; imssr seals every index it writes, so neither is loaded."""
    path = str(tmp_path / "replay.npz")
    _fill(_host()).save(path)
    fault(path)
    with pytest.raises(ReplayFileError, match=f"^{re.escape(message.format(path))}$"):
        _host().load(path)
    with pytest.raises(ReplayFileError, match=f"^{re.escape(message.format(path))}$"):
        replay_files(path)


def test_a_single_frames_file_without_its_checksum_is_refused(tmp_path):
    """An index of the layout before frame files always named its frames' sha256: one that does
    not (sealed by someone else) is not loaded unverified."""
    path = str(tmp_path / "replay.npz")
    _fill(_host()).save(path)
    as_single_file_replay(path, checksum=False)
    with pytest.raises(ReplayFileError, match=r"^replay buffer \S+replay\.npz holds no checksum of its frames$"):
        _host().load(path)
