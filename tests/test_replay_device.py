"""``train.replay_device``: where ``auto`` puts the frames (a pure choice, checked with made-up
memory figures), the one-line errors, and training with the tensor store: the same run as with
the host store, and an exact resume across stores (the tensor store on the CPU)."""
import os

import numpy as np
import pytest
import torch

from conftest import assert_same_nets, tiny_config, train_run, without_timing
from imssr.cli import main
from imssr.config import apply_overrides
from imssr.errors import ImssrError
from imssr.presets import make_config
from imssr.replay import (DiskFrameReplayBuffer, FrameReplayBuffer, TensorFrameReplayBuffer, choose_replay_device,
                          replay_placement)
from imssr.replay.device import REPLAY_DEVICE_MARGIN_BYTES
from imssr.training import Trainer
from imssr.training import build
from imssr.training.logger import read_csv

CPU, GPU = torch.device("cpu"), torch.device("cuda", 0)
GB = 10**9
FRAMES_500K = 500_000 * 3 * 100 * 100
"""The paper's 500k transitions at 100 px: 15 GB of frames."""


# -- the choice ---------------------------------------------------------------------------------

def test_the_paper_buffer_is_15_gb_of_frames():
    assert FRAMES_500K == 15 * GB


def test_auto_puts_the_frames_on_a_gpu_with_room_for_them_and_the_model():
    placed = choose_replay_device("auto", GPU, FRAMES_500K, free_nbytes=79 * GB)
    assert placed.device == GPU
    assert placed.reason == ("imssr: replay frames on cuda:0 (train.replay_device=auto: 15.0 GB of frames + "
                             "4.0 GB for the model, 79.0 GB free on cuda:0)")
    exactly = choose_replay_device("auto", GPU, FRAMES_500K, FRAMES_500K + REPLAY_DEVICE_MARGIN_BYTES)
    assert exactly.device == GPU


def test_auto_keeps_the_frames_on_the_host_when_the_gpu_lacks_room():
    for free in (15 * GB, FRAMES_500K + REPLAY_DEVICE_MARGIN_BYTES - 1, 0):
        placed = choose_replay_device("auto", GPU, FRAMES_500K, free_nbytes=free)
        assert placed.device == CPU, free
        assert placed.reason.startswith("imssr: replay frames in host memory, the GPU lacks room "
                                        "(train.replay_device=auto: 15.0 GB of frames + 4.0 GB")
        assert "\n" not in placed.reason
    # A small buffer fits a small GPU.
    assert choose_replay_device("auto", GPU, 3 * GB, free_nbytes=8 * GB).device == GPU


def test_runs_sharing_a_gpu_fit_together_whatever_each_sees_free_at_its_start():
    # Four runs at --gpus-per-run 0.25 on an 80 GB GPU start together: each sees it all free.
    total = 80 * GB
    placed = [choose_replay_device("auto", GPU, FRAMES_500K, free_nbytes=total - 1 * GB, share=0.25,
                                   total_nbytes=total) for _ in range(4)]
    assert all(p.device == GPU for p in placed)
    assert 4 * (FRAMES_500K + REPLAY_DEVICE_MARGIN_BYTES) <= total
    assert placed[0].reason == ("imssr: replay frames on cuda:0 (train.replay_device=auto: 15.0 GB of frames + "
                                "4.0 GB for the model, 20.0 GB for this run on cuda:0, its share 0.25 of 80.0 GB)")
    # Five at 0.2: 16 GB each cannot hold 19 GB; every one keeps its frames on the host.
    fifth = choose_replay_device("auto", GPU, FRAMES_500K, free_nbytes=total, share=0.2, total_nbytes=total)
    assert fifth.device == CPU and "the GPU lacks room" in fifth.reason
    # A share never counts memory that is not free (another process holds it).
    taken = choose_replay_device("auto", GPU, FRAMES_500K, free_nbytes=10 * GB, share=0.5, total_nbytes=total)
    assert taken.device == CPU and "10.0 GB for this run" in taken.reason
    # A whole GPU: its free memory, as before.
    assert choose_replay_device("auto", GPU, FRAMES_500K, 79 * GB, share=1.0, total_nbytes=total) == \
        choose_replay_device("auto", GPU, FRAMES_500K, 79 * GB)


def test_a_gpu_share_is_validated():
    cfg = make_config("curl", "walker_walk")
    assert cfg.train.gpu_share == 1.0
    for bad in ("0", "1.5", "-0.25"):
        with pytest.raises(ImssrError, match=r"^train.gpu_share must be in \(0, 1\]"):
            apply_overrides(cfg, [f"train.gpu_share={bad}"]).validate()


def test_a_cpu_agent_keeps_its_frames_on_the_host_without_a_word():
    assert choose_replay_device("auto", CPU, FRAMES_500K, free_nbytes=None) == choose_replay_device(
        "cpu", CPU, FRAMES_500K, None)
    assert choose_replay_device("auto", CPU, FRAMES_500K, None).reason is None
    assert choose_replay_device("cpu", GPU, FRAMES_500K, 79 * GB).device == CPU  # asked for: the host


def test_cuda_is_the_agents_gpu_and_needs_one():
    assert choose_replay_device("cuda", GPU, FRAMES_500K, None).device == GPU
    with pytest.raises(ImssrError, match=r"^train.replay_device=cuda needs the agent on a GPU, but "
                                         r"train.device is cpu; use --device cuda or"):
        choose_replay_device("cuda", CPU, FRAMES_500K, None)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks a machine without CUDA")
def test_cuda_on_a_machine_without_it_is_one_line():
    with pytest.raises(ImssrError, match=r"^train.replay_device=cuda requested but CUDA is not available; "
                                         r"use --set train.replay_device=cpu$"):
        replay_placement("cuda", CPU, FRAMES_500K)
    assert replay_placement("auto", CPU, FRAMES_500K).device == CPU


def test_a_bad_replay_device_is_one_line(capsys):
    cfg = make_config("curl", "walker_walk")
    assert cfg.train.replay_device == "auto"
    with pytest.raises(ImssrError, match=r"^train.replay_device must be one of cpu, cuda, auto, disk, got 'tpu'$"):
        apply_overrides(cfg, ["train.replay_device=tpu"]).validate()
    assert main(["train", "--algo", "curl", "--task", "cartpole_swingup_sparse",
                 "--set", "train.replay_device=tpu"]) == 2
    err = capsys.readouterr().err
    assert err == "imssr: error: train.replay_device must be one of cpu, cuda, auto, disk, got 'tpu'\n"


# -- training with the tensor store ------------------------------------------------------------

def _cfg():
    # 3 episodes of cartpole on 60 px frames, killed after the second.  Every agent step from 200
    # samples a batch (the buffer's part); the networks learn from every 5th (cheaper), on both
    # sides of the kill.
    cfg = tiny_config("curl", steps=375, seed_steps=200, eval_every_steps=0, checkpoint_every_steps=125)
    cfg.env.image_size, cfg.agent.crop_size, cfg.agent.encoder_filters = 60, 52, 8
    a = cfg.agent
    a.critic_update_every = a.actor_update_every = a.target_update_every = cfg.aux.update_every = 5
    return cfg


REAL_MAKE_REPLAY_BUFFER = build.make_replay_buffer


def _use(monkeypatch, store: str) -> None:
    """Have the trainer build ``store``: ``host`` (what it builds on a CPU) or ``tensor`` (the
    tensor store, here on the CPU)."""
    def tensor(device, *args, frames_file=None, reserve_slots=0, **kwargs):
        assert frames_file is None  # frames on disk are the host store's; these tests keep them in memory
        return TensorFrameReplayBuffer(*args, **kwargs, device="cpu")

    monkeypatch.setattr(build, "make_replay_buffer", REAL_MAKE_REPLAY_BUFFER if store == "host" else tensor)


def _train(out, stop_at=None, resume=False, replay_device="auto"):
    cfg = _cfg()
    cfg.train.replay_device = replay_device
    return train_run(cfg, out, stop_at, resume)


def _assert_same_run(a, a_dir, b, b_dir):
    assert a.step == b.step == 375
    assert_same_nets(a.agent, b.agent)
    assert a.replay.state_dict() == b.replay.state_dict()
    assert np.array_equal(np.asarray(a.replay.frames[:a.replay.size]), np.asarray(b.replay.frames[:b.replay.size]))
    for name in ("train.csv", "eval.csv"):
        assert without_timing(read_csv(os.path.join(a_dir, name))) == \
            without_timing(read_csv(os.path.join(b_dir, name))), name


@pytest.fixture(scope="module")
def host_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("host")
    return str(out), _train(out)


def test_the_default_on_a_cpu_is_the_host_store(tmp_path, capsys):
    t = Trainer(_cfg(), str(tmp_path))
    try:
        assert type(t.replay) is FrameReplayBuffer and t.replay_placement.reason is None
    finally:
        t.close()
    assert "replay frames" not in capsys.readouterr().out


@pytest.mark.parametrize("first, then", [("tensor", "tensor"), ("host", "tensor"), ("tensor", "host")])
def test_a_killed_run_resumes_exactly_with_either_store(host_run, monkeypatch, tmp_path, first, then):
    _use(monkeypatch, first)
    part = _train(tmp_path, stop_at=250)
    assert part.step == 250 and isinstance(part.replay, TensorFrameReplayBuffer) == (first == "tensor")
    _use(monkeypatch, then)
    # train.replay_device may change on resume (it changes where the frames live, not the run).
    resumed = _train(tmp_path, resume=True, replay_device="cpu" if then == "host" else "auto")
    assert isinstance(resumed.replay, TensorFrameReplayBuffer) == (then == "tensor")
    _assert_same_run(resumed, str(tmp_path), host_run[1], host_run[0])


# -- frames on disk (train.replay_device=disk) ---------------------------------------------------

def test_frames_on_disk_are_the_frames_in_memory(tmp_path):
    """The disk store (a memory-mapped file) draws the batches and writes the files of the
    in-memory store through a wrap of its ring, loads what the other saved, and leaves no file
    once closed."""
    shape, path = (3, 20, 20), str(tmp_path / "frames.mmap")
    mem = FrameReplayBuffer(300, shape, 2, seed=7, physics_dim=3)
    disk = DiskFrameReplayBuffer(300, shape, 2, seed=7, physics_dim=3, path=path, reserve_slots=300)
    assert os.path.getsize(path) == 300 * 3 * 20 * 20
    rng = np.random.default_rng(0)
    for t in range(450):
        first, frame = (rng.integers(0, 256, shape, dtype=np.uint8) for _ in range(2))
        action, reward, physics = rng.uniform(-1, 1, 2), float(rng.normal()), rng.normal(size=3)
        for buf in (mem, disk):
            if t % 50 == 0:
                buf.add_first(first, physics, t)
            buf.add(action, reward, 1.0, frame, physics, t + 1)
    for _ in range(3):
        a, b = mem.sample_batch(16, "cpu"), disk.sample_batch(16, "cpu")
        assert all(torch.equal(a[k], b[k]) for k in a)
    for buf, where in ((mem, "mem"), (disk, "disk")):
        os.makedirs(tmp_path / where)
        buf.save(str(tmp_path / where / "replay-000000450.npz"))
    saved = {where: sorted(os.listdir(tmp_path / where)) for where in ("mem", "disk")}
    assert saved["mem"] == saved["disk"] and len(saved["mem"]) == 2
    frames = next(name for name in saved["mem"] if name.endswith(".npy"))
    assert (tmp_path / "mem" / frames).read_bytes() == (tmp_path / "disk" / frames).read_bytes()
    with np.load(tmp_path / "mem" / "replay-000000450.npz") as m, np.load(tmp_path / "disk" / "replay-000000450.npz") as d:
        assert m.files == d.files and all(np.array_equal(m[k], d[k]) for k in m.files)
    again = DiskFrameReplayBuffer(300, shape, 2, seed=0, physics_dim=3, path=str(tmp_path / "again.mmap"))
    again.load(str(tmp_path / "mem" / "replay-000000450.npz"), mem.state_dict()["rng"])
    a, b = mem.sample_batch(16, "cpu"), again.sample_batch(16, "cpu")
    assert all(torch.equal(a[k], b[k]) for k in a)
    disk.close()
    again.close()
    assert not os.path.exists(path) and not os.path.exists(tmp_path / "again.mmap")


def test_a_run_with_its_frames_on_disk_resumes_to_the_run_with_them_in_memory(host_run, tmp_path):
    """``train.replay_device=disk``: the frames in ``RUN/replay-frames.mmap`` while the run trains,
    gone when it stops; stopped and resumed, it ends as the run with its frames in memory."""
    from imssr.rundir import RunDir

    part = _train(tmp_path, stop_at=250, replay_device="disk")
    assert type(part.replay) is DiskFrameReplayBuffer and part.replay.path == RunDir(str(tmp_path)).frames_file
    assert not os.path.exists(part.replay.path)
    resumed = _train(tmp_path, resume=True, replay_device="disk")
    _assert_same_run(resumed, str(tmp_path), host_run[1], host_run[0])
