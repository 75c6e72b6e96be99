"""Faults around a run's files: two writers, a full disk, damaged files, file permissions.

Tiny runs on cartpole (125 agent steps per episode, checkpoints at every episode end) with a
seed phase that lasts almost to the end, so that they cost seconds and still make a few updates.
"""
import contextlib
import errno
import fcntl
import os
import re
import shutil
import stat
import subprocess
import sys
import threading

import numpy as np
import pytest
import torch

from conftest import (a_checkpoint, as_single_file_replay, assert_same_nets, fill_fs, filled_buffer, tiny_config, train_run,
                      without_timing)
from imssr.cli import main
from imssr.errors import ImssrError
from imssr.files import atomic_write_csv, atomic_write_text
from imssr.replay import FrameReplayBuffer
from imssr.training import Trainer
from imssr.training.evaluate import evaluate_run
from imssr.rundir import RunDir
from imssr.rundir.checkpoint import CheckpointDamaged, load_checkpoint
from imssr.rundir.lock import LOCK_FILE, DirectoryLock
from imssr.training.logger import CSVLog, Logger, read_csv

TASK = "cartpole_swingup_sparse"
NO_SPACE = r"no space left on (?P<device>/\S*) while writing (?P<path>\S+) \(\d+\.\d+ MB needed\)"


def _cfg():
    # 3 episodes; learning starts at agent step 360, so the last 15 steps update the agent.
    cfg = tiny_config("curl", TASK, steps=375, seed_steps=360, eval_every_steps=0,
                      checkpoint_every_steps=125, keep_checkpoints=2)
    return cfg


def _train(out, stop_at=None, resume=False, **kw):
    return train_run(_cfg(), out, stop_at, resume, **kw)


_strip = without_timing


def _assert_same_run(a, a_dir, b, b_dir):
    """Two finished runs reached the same weights, replay buffer and logs."""
    assert a.step == b.step
    assert_same_nets(a.agent, b.agent)
    assert a.replay.size == b.replay.size
    assert np.array_equal(a.replay.frames[: a.replay.size], b.replay.frames[: b.replay.size])
    for name in ("train.csv", "eval.csv"):
        assert _strip(read_csv(os.path.join(a_dir, name))) == _strip(read_csv(os.path.join(b_dir, name))), name


@pytest.fixture(scope="module")
def full(tmp_path_factory):
    out = tmp_path_factory.mktemp("full")
    return str(out), _train(out)


@pytest.fixture(scope="module")
def stopped(tmp_path_factory):
    """A run stopped at the episode end with its checkpoint at agent step 250 (step-125 and
    step-250 retained)."""
    out = tmp_path_factory.mktemp("stopped")
    _train(out, stop_at=250)
    return str(out)


@pytest.fixture
def run(stopped, tmp_path):
    """A private copy of the stopped run."""
    path = str(tmp_path / "run")
    shutil.copytree(stopped, path)
    return path


REPLAY_250 = ["replay-000000250.npz", "replay-frames-000000000000-000000000126.npy",
              "replay-frames-000000000126-000000000252.npy"]
"""The replay files of the checkpoint at agent step 250: the index and one frame file per save
(125 agent steps and an episode's first frame each)."""


def _ckpt(run_dir, name):
    return os.path.join(run_dir, "checkpoints", name)


def _flip(path, count=64):
    """Invert ``count`` bytes in the middle of ``path``."""
    data = bytearray(open(path, "rb").read())
    mid = len(data) // 2
    data[mid:mid + count] = bytes(b ^ 0xFF for b in data[mid:mid + count])
    with open(path, "wb") as fh:
        fh.write(data)


# -- two writers ---------------------------------------------------------------------------

HOLD = ("import sys\nfrom imssr.rundir.lock import DirectoryLock\n"
        "DirectoryLock(sys.argv[1]).acquire()\nprint('locked', flush=True)\nsys.stdin.read()\n")


@contextlib.contextmanager
def held_by_another_process(directory):
    child = subprocess.Popen([sys.executable, "-c", HOLD, str(directory)], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "locked"
        yield child
    finally:
        if child.poll() is None:
            child.kill()
        child.wait()


def test_local_holder_names_only_a_live_holder_on_this_machine(tmp_path):
    """What a local Ray sweep signals when it stops: the process that holds a run's lock now."""
    from imssr.rundir.lock import local_holder

    out = tmp_path / "run"
    out.mkdir()
    assert local_holder(str(out)) is None  # no lock file
    with held_by_another_process(out) as child:
        assert local_holder(str(out)) == child.pid
        child.kill()
        child.wait()
    assert (out / LOCK_FILE).exists() and local_holder(str(out)) is None  # left by a dead process
    with held_by_another_process(out) as child:
        (out / LOCK_FILE).write_text(f"{child.pid} another-host\n")  # a run on a shared file system
        assert local_holder(str(out)) is None


def test_a_second_writer_is_refused_and_a_dead_ones_lock_is_taken_over(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    # Logs of a run that never checkpointed: the refused writer must leave them.
    (out / "train.csv").write_text("frame,step\n1000,125\n")
    (out / "tb").mkdir()
    (out / "tb" / "events").write_text("x")
    with held_by_another_process(out) as child:
        with pytest.raises(ImssrError, match=rf"^{re.escape(str(out))} is in use by PID {child.pid}\b"):
            Trainer(_cfg(), str(out))
        code = main(["train", "--algo", "curl", "--task", TASK, "--steps", "10", "--out", str(out),
                     "--no-progress"])
        err = capsys.readouterr().err
        assert code == 2 and err.count("\n") == 1 and f"{out} is in use by PID {child.pid}" in err
        child.kill()
    assert (out / "train.csv").read_text() == "frame,step\n1000,125\n" and (out / "tb" / "events").exists()
    # A log with a row is part of a run, which a fresh start refuses (tested on its own below);
    # here the lock is what matters.
    (out / "train.csv").unlink()
    # kill -9 left the lock file behind; the kernel dropped the lock with the process.
    assert (out / LOCK_FILE).exists()
    t = Trainer(_cfg(), str(out))
    try:
        assert (out / LOCK_FILE).read_text().split()[0] == str(os.getpid())
    finally:
        t.close()
    assert not (out / LOCK_FILE).exists()


def test_a_resume_in_a_second_process_is_refused_and_evaluate_still_reads(run, capsys):
    t = Trainer(_cfg(), run, resume=True)
    try:
        proc = subprocess.run([sys.executable, "-m", "imssr", "train", "--resume", "--out", run, "--no-progress"],
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 2, proc.stderr
        assert proc.stderr.count("\n") == 1 and f"{run} is in use by PID {os.getpid()}" in proc.stderr
        # Readers take no lock.
        assert main(["evaluate", "--run", run, "--episodes", "1"]) == 0
        assert "step 250" in capsys.readouterr().out
    finally:
        t.close()


def test_two_sweeps_over_one_root_and_the_sweep_lock(tmp_path, monkeypatch):
    from imssr.sweep import sweep
    from imssr.sweep.grid import SweepConfig

    root = tmp_path / "sweep"
    cfg = SweepConfig(root=str(root), algos=["curl"], tasks=[TASK], seeds=[1], steps=10)
    with held_by_another_process(root) as child:
        with pytest.raises(ImssrError, match=rf"{re.escape(str(root))} is in use by PID {child.pid}"):
            sweep.run_sweep(cfg, progress=False)

    def body(cfg, launcher, progress, poll_s):  # the sweep holds its root while it runs
        with pytest.raises(ImssrError, match=f"is in use by PID {os.getpid()}"):
            DirectoryLock(str(root)).acquire()
        return []

    monkeypatch.setattr(sweep, "_run_sweep", body)
    assert sweep.run_sweep(cfg, progress=False) == []
    DirectoryLock(str(root)).acquire().release()  # released when the sweep ends


def test_a_refused_run_releases_its_directory(tmp_path):
    out = tmp_path / "new" / "run"
    with pytest.raises(ImssrError, match="nothing to resume"):
        Trainer(_cfg(), str(out), resume=True)
    assert not (tmp_path / "new").exists()  # nothing left behind, and no lock held
    DirectoryLock(str(out)).acquire().release()


# -- damaged files -------------------------------------------------------------------------

def _snapshot(directory):
    """Every file under ``directory`` with its bytes."""
    files = {}
    for root, _, names in os.walk(directory):
        for name in names:
            path = os.path.join(root, name)
            with open(path, "rb") as fh:
                files[os.path.relpath(path, directory)] = fh.read()
    return files


@pytest.mark.parametrize("missing", ["latest.pt", "every checkpoint"])
def test_a_fresh_start_refuses_any_part_of_a_run_and_deletes_nothing(run, missing, tmp_path, capsys):
    """A fresh `imssr train --out RUN` on a run whose latest.pt is gone: one line, nothing deleted."""
    config = str(tmp_path / "config.json")
    shutil.copy(RunDir(run).config_path, config)
    os.unlink(_ckpt(run, "latest.pt"))
    if missing == "every checkpoint":
        for name in os.listdir(os.path.join(run, "checkpoints")):
            os.unlink(_ckpt(run, name))
    RunDir(run).write_status("finished", step=250)
    before = _snapshot(run)
    args = ["train", "--config", config, "--steps", "1", "--out", run]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and err.startswith(f"imssr: error: {run} already holds ")
    if missing == "latest.pt":
        assert "step-000000250.pt" in err and "pass --resume to continue it" in err
    else:
        assert "train.csv" in err and "no checkpoint to resume from" in err and "--resume" not in err
    after = _snapshot(run)
    after.pop(LOCK_FILE, None), before.pop(LOCK_FILE, None)
    assert after == before
    assert RunDir(run).status() == "finished"


def test_numbered_checkpoints_are_real_copies(stopped):
    latest, numbered = RunDir(stopped).latest, _ckpt(stopped, "step-000000250.pt")
    assert os.stat(latest).st_nlink == 1 and os.stat(numbered).st_nlink == 1
    assert not os.path.samefile(latest, numbered)
    assert open(latest, "rb").read() == open(numbered, "rb").read()
    assert sorted(os.listdir(os.path.join(stopped, "checkpoints"))) == [
        "latest.pt", *REPLAY_250, "step-000000125.pt", "step-000000250.pt"]


def test_flipped_bytes_in_latest_are_caught_and_resume_falls_back_exactly(run, full, capsys):
    _flip(RunDir(run).latest)
    with pytest.raises(CheckpointDamaged, match=r"latest\.pt is damaged \(checksum mismatch\)$"):
        load_checkpoint(RunDir(run).latest)
    assert load_checkpoint(_ckpt(run, "step-000000250.pt")).step == 250  # the copy is intact
    resumed = _train(run, resume=True)
    out = capsys.readouterr().out
    assert ("imssr: latest.pt is damaged (checksum mismatch); resuming from step-000000250.pt "
            "at agent step 250\n") in out
    assert "refilling" not in out  # the copy holds latest's step: its replay buffer is there
    _assert_same_run(resumed, run, full[1], full[0])


def test_an_older_checkpoint_resumes_with_a_refilled_buffer(run, capsys):
    _flip(RunDir(run).latest)
    _flip(_ckpt(run, "step-000000250.pt"))
    t = _train(run, resume=True)
    out = capsys.readouterr().out
    assert ("imssr: latest.pt is damaged (checksum mismatch); resuming from step-000000125.pt "
            "at agent step 125\n") in out
    assert "no replay buffer was kept for step-000000125.pt; refilling it with random actions" in out
    assert t.step == 375 and load_checkpoint(RunDir(run).latest).step == 375
    _flip(RunDir(run).latest)
    _flip(_ckpt(run, "step-000000375.pt"))
    _flip(_ckpt(run, "step-000000250.pt"))
    with pytest.raises(ImssrError, match=r"latest\.pt is damaged \(checksum mismatch\), and no retained "
                                         r"step-\*\.pt checkpoint .* is valid"):
        Trainer(_cfg(), run, resume=True)


@pytest.mark.parametrize("fault", ["damaged", "missing"])
def test_a_lost_replay_buffer_needs_refill_buffer(run, fault, capsys):
    replay = _ckpt(run, "replay-000000250.npz")
    if fault == "damaged":
        _flip(_ckpt(run, REPLAY_250[2]))
        expected = r"replay-frames-000000000126-000000000252\.npy is damaged \(checksum mismatch\)"
    else:
        os.unlink(replay)
        expected = r"replay buffer file not found: .*replay-000000250\.npz"
    with pytest.raises(ImssrError, match=expected + r"; `imssr train --resume --refill-buffer` continues"):
        Trainer(_cfg(), run, resume=True)
    t = Trainer(_cfg(), run, resume=True, refill_buffer=True)  # the failed attempt released the run
    try:
        assert t.step == 250 and t.state.learning_starts == 250 + 360 and t.replay.size == 0
    finally:
        t.close()
    assert "refilling it with random actions until agent step 610" in capsys.readouterr().out
    # Through the CLI, which trains the last episode and saves a buffer again.
    assert main(["train", "--resume", "--refill-buffer", "--out", run, "--no-progress"]) == 0
    state = load_checkpoint(RunDir(run).latest)
    assert state.step == 375 and os.path.exists(_ckpt(run, state.replay_file))
    assert main(["train", "--refill-buffer", "--out", run]) == 2
    assert "--refill-buffer goes with --resume" in capsys.readouterr().err


def test_files_without_checksums_are_not_loaded(run, capsys):
    """imssr seals every checkpoint and replay index it writes: a resume never loads one without a
    seal unverified.  An unsealed latest.pt falls back to the retained copy; an unsealed replay
    index stops the resume, naming --refill-buffer."""
    path = RunDir(run).latest
    torch.save(dict(load_checkpoint(path).to_state(), format_version=1), path)
    t = Trainer(_cfg(), run, resume=True)
    t.close()
    assert t.step == 250 and ("imssr: latest.pt is damaged (not an imssr checkpoint); resuming from "
                              "step-000000250.pt at agent step 250\n") in capsys.readouterr().out
    replay = _ckpt(run, "replay-000000250.npz")
    with np.load(replay) as data:
        fields = {k: data[k] for k in data.files}
    with open(replay, "wb") as fh:
        np.savez(fh, **fields)
    with pytest.raises(ImssrError, match=rf"^{re.escape(replay)} is not a replay buffer imssr wrote: it carries no "
                                         r"imssr checksum; `imssr train --resume --refill-buffer` continues"):
        Trainer(_cfg(), run, resume=True)


def test_a_replay_buffer_in_one_frames_file_resumes_exactly_and_is_verified(run, full):
    """A checkpoint whose replay buffer is one ``.frames.npy`` beside its index (imssr before frame
    files) resumes exactly; its next save writes frame files and drops the single file."""
    frames = as_single_file_replay(_ckpt(run, "replay-000000250.npz"))
    assert sorted(os.listdir(os.path.join(run, "checkpoints")))[1:3] == [
        "replay-000000250.npz", "replay-000000250.npz.frames.npy"]
    t = Trainer(_cfg(), run, resume=True)
    t.close()
    assert t.replay.size == frames.shape[0] and np.array_equal(t.replay.frames[: t.replay.size], frames)
    _assert_same_run(_train(run, resume=True), run, full[1], full[0])
    assert not [f for f in os.listdir(os.path.join(run, "checkpoints")) if f.endswith(".frames.npy")]


def test_a_damaged_single_frames_file_is_caught(run):
    as_single_file_replay(_ckpt(run, "replay-000000250.npz"))
    _flip(_ckpt(run, "replay-000000250.npz.frames.npy"))
    with pytest.raises(ImssrError, match=r"replay-000000250\.npz\.frames\.npy is damaged \(checksum mismatch\)"):
        Trainer(_cfg(), run, resume=True)


def test_evaluate_picks_a_checkpoint(run, capsys):
    assert main(["evaluate", "--run", run, "--episodes", "1", "--checkpoint", "125"]) == 0
    assert "step 125" in capsys.readouterr().out
    assert main(["evaluate", "--run", run, "--episodes", "1", "--checkpoint", "999"]) == 2
    assert "no checkpoint at agent step 999" in capsys.readouterr().err
    _flip(RunDir(run).latest)
    assert main(["evaluate", "--run", run, "--episodes", "1", "--checkpoint", RunDir(run).latest]) == 2
    assert "latest.pt is damaged (checksum mismatch)" in capsys.readouterr().err
    # Without --checkpoint, a damaged latest.pt falls back as --resume does.
    assert main(["evaluate", "--run", run, "--episodes", "1"]) == 0
    out = capsys.readouterr().out
    assert "latest.pt is damaged (checksum mismatch); evaluating step-000000250.pt at agent step 250" in out


def test_two_evaluations_of_one_run_do_not_interleave_their_rows(run):
    """Another evaluation holds evaluate.csv and writes its rows in two pieces; this one's rows,
    ready meanwhile, go in after them, together."""
    path = os.path.join(run, "evaluate.csv")
    first_scene = threading.Event()

    def log(line):
        if ": return " in line:
            first_scene.set()

    worker = threading.Thread(target=evaluate_run, args=(run,),
                              kwargs=dict(episodes=1, modes="training,color_easy", log=log))
    with open(path, "a") as other:
        fcntl.flock(other, fcntl.LOCK_EX)
        other.write("frame,step,mode,return_mean,return_std,episodes,return_min,return_max,wall_time\n")
        other.write("0,0,other-first,0,0,1,0,0,\n")
        other.flush()
        worker.start()
        assert first_scene.wait(timeout=600)
        other.write("0,0,other-second,0,0,1,0,0,\n")
    worker.join()
    assert [r["mode"] for r in read_csv(path)] == ["other-first", "other-second", "training", "color_easy"]


# -- a full disk ---------------------------------------------------------------------------

def _after_failed_save(run_dir):
    """The previous checkpoint is whole and nothing of the failed save is left."""
    assert load_checkpoint(RunDir(run_dir).latest).step == 250
    assert sorted(os.listdir(os.path.join(run_dir, "checkpoints"))) == [
        "latest.pt", *REPLAY_250, "step-000000125.pt", "step-000000250.pt"]


def test_checkpoint_write_on_a_full_disk_keeps_the_previous_one(run, full, monkeypatch):
    def full_disk(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    t = Trainer(_cfg(), run, resume=True)
    monkeypatch.setattr(torch, "save", full_disk)
    try:
        with pytest.raises(ImssrError) as err:
            t.train()
    finally:
        t.close()
        monkeypatch.undo()
    match = re.fullmatch(NO_SPACE, str(err.value))
    assert match and match["path"] == RunDir(run).latest, str(err.value)
    _after_failed_save(run)
    _assert_same_run(_train(run, resume=True), run, full[1], full[0])


@pytest.mark.parametrize("error", [OSError(errno.ENOSPC, "No space left on device"),
                                   OSError("7560000 requested and 4239232 written"),
                                   OSError(errno.EDQUOT, "Disk quota exceeded")])
def test_replay_write_on_a_full_disk(tmp_path, monkeypatch, error):
    buf = filled_buffer(60, capacity=100, size=8)
    path = str(tmp_path / "replay.npz")
    buf.save(path)
    before = sorted(os.listdir(tmp_path))
    buf.add(np.zeros(1), 0.0, 1.0, np.zeros((3, 8, 8), np.uint8))  # one new frame for the next save

    def half_then_fail(writer, slot, count):
        writer.write(bytes(100))
        raise error

    monkeypatch.setattr(buf, "_write_slots", half_then_fail)
    with pytest.raises(ImssrError) as err:
        buf.save(path)
    assert re.fullmatch(NO_SPACE.replace("no space left", r"no space left( \(disk quota exceeded\))?"),
                        str(err.value)), str(err.value)
    assert f"while writing {tmp_path}/replay-frames-000000000062-000000000063.npy (" in str(err.value)
    monkeypatch.undo()
    assert sorted(os.listdir(tmp_path)) == before == ["replay-frames-000000000000-000000000062.npy", "replay.npz"]
    FrameReplayBuffer(100, (3, 8, 8), 1).load(path)  # the old files are whole


def test_a_run_on_a_full_file_system_stops_in_one_line_and_resumes(stopped, full, tiny_fs):
    mnt = tiny_fs("64m")
    run = os.path.join(mnt, "run")
    shutil.copytree(stopped, run)
    filler = fill_fs(mnt, leave=1_000_000)  # room for logs, not for the next replay buffer
    t = Trainer(_cfg(), run, resume=True)
    try:
        with pytest.raises(ImssrError) as err:
            t.train()
    finally:
        t.close()
    match = re.fullmatch(NO_SPACE, str(err.value))
    assert match and match["device"] == mnt, str(err.value)
    assert match["path"] == _ckpt(run, "replay-frames-000000000252-000000000378.npy")
    _after_failed_save(run)
    os.unlink(filler)
    _assert_same_run(_train(run, resume=True), run, full[1], full[0])


def test_every_writer_reports_a_full_file_system(tiny_fs):
    mnt = tiny_fs("2m")
    run = os.path.join(mnt, "run")
    RunDir(run).save_checkpoint(a_checkpoint(step=1, agent={"w": torch.zeros(10)}))
    with pytest.raises(ImssrError, match=rf"^no space left on {mnt} while writing {RunDir(run).latest} "
                                         r"\(4\.0 MB needed\)$"):
        RunDir(run).save_checkpoint(a_checkpoint(step=2, agent={"w": torch.zeros(1_000_000)}))
    assert load_checkpoint(RunDir(run).latest).step == 1
    assert sorted(os.listdir(os.path.join(run, "checkpoints"))) == ["latest.pt", "step-000000001.pt"]
    notes = os.path.join(mnt, "notes.json")
    with pytest.raises(ImssrError, match=rf"^no space left on {mnt} while writing {notes} \(3\.0 MB needed\)$"):
        atomic_write_text(notes, "x" * 3_000_000)
    with pytest.raises(ImssrError, match=rf"^no space left on {mnt} while writing {mnt}/table.csv$"):
        atomic_write_csv(os.path.join(mnt, "table.csv"), ["a"], [["x" * 1000]] * 3000)
    buf = filled_buffer(60, capacity=100, size=100)  # 1.8 MB of frames
    log = CSVLog(os.path.join(run, "train.csv"), ["frame", "note"])
    fill_fs(mnt)
    with pytest.raises(ImssrError, match=rf"^no space left on {mnt} while writing .*replay-frames-0+-0+62\.npy"):
        buf.save(os.path.join(run, "replay.npz"))
    with pytest.raises(ImssrError, match=rf"^no space left on {mnt} while writing {run}/train.csv$"):
        for i in range(10_000):  # fills the file's last page first
            log.write({"frame": i, "note": "x" * 100})
    assert not [f for f in os.listdir(mnt) + os.listdir(run) if f.startswith(".tmp-")]


# -- permissions ---------------------------------------------------------------------------

@pytest.mark.parametrize("umask", [0o022, 0o077])
def test_output_files_honour_the_umask(tmp_path, umask):
    run = tmp_path / "run"
    old = os.umask(umask)
    try:
        atomic_write_text(str(run / "config.json"), "{}\n")
        atomic_write_csv(str(run / "table.csv"), ["a"], [[1]])
        CSVLog(str(run / "train.csv"), ["frame"]).write({"frame": 1})
        RunDir(str(run)).save_checkpoint(a_checkpoint(step=3, replay_file="replay-000000003.npz"), keep=1,
                                         replay=filled_buffer(60, capacity=100, size=8))
        lock = DirectoryLock(str(run)).acquire()
        lock_mode = stat.S_IMODE(os.stat(run / LOCK_FILE).st_mode)
        lock.release()
    finally:
        os.umask(old)
    files = ["config.json", "table.csv", "train.csv", "checkpoints/replay-000000003.npz",
             "checkpoints/replay-frames-000000000000-000000000062.npy", "checkpoints/latest.pt",
             "checkpoints/step-000000003.pt"]
    modes = {f: oct(stat.S_IMODE(os.stat(run / f).st_mode)) for f in files}
    assert modes == {f: oct(0o666 & ~umask) for f in files}
    assert lock_mode == 0o666 & ~umask


def test_a_runs_files_are_not_private(stopped):
    umask = os.umask(0)
    os.umask(umask)
    for name in ("config.json", "train.csv", "checkpoints/latest.pt", "checkpoints/replay-000000250.npz"):
        assert stat.S_IMODE(os.stat(os.path.join(stopped, name)).st_mode) == 0o666 & ~umask, name


def test_a_missing_tensorboard_keeps_the_csv_logs_and_says_so_in_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)  # its import fails as when not installed
    log = Logger(RunDir(str(tmp_path / "run")), tensorboard=True)
    log.log_train({"frame": 8, "step": 1, "episode_return": 1.0})
    log.close()
    assert log.tb is None and not os.path.exists(tmp_path / "run" / "tb")
    assert [r["episode_return"] for r in read_csv(str(tmp_path / "run" / "train.csv"))] == ["1"]
    assert capsys.readouterr().out == \
        "imssr: warning: TensorBoard is not installed: train.csv and eval.csv keep every row\n"


def test_tensorboard_and_sweep_log_on_a_full_file_system(tiny_fs, capfd):
    """TensorBoard's writer thread and the sweep's log append each give the one disk-full line:
    a warning that turns TensorBoard off (the CSV logs go on), and the attempt's error."""
    from imssr.sweep.runner import execute_runs

    mnt = tiny_fs("1m")
    run = os.path.join(mnt, "run")
    log = Logger(RunDir(run), tensorboard=True)
    fill_fs(mnt)
    for frame in range(100_000):  # queued events reach the disk at a flush
        log.log_train({"frame": frame, "step": frame, "episode_return": 1.0})
        if log.tb is None:
            break
        if frame % 100 == 0:
            log.tb.flush()
    out, err = capfd.readouterr()
    assert out == (f"imssr: warning: no space left on {mnt} while writing {run}/tb: TensorBoard stops here "
                   "(train.csv and eval.csv keep every row)\n")
    log.close()
    assert "Traceback" not in err  # nor the writer thread's
    result = execute_runs([os.path.join(mnt, "sweep-run")], 10, 1)[0]
    assert not result["ok"] and result["returncode"] is None
    assert re.fullmatch(rf"no space left on {mnt} while writing {mnt}/sweep-run/sweep.log", result["error"])


def test_a_full_tensorboard_disk_at_the_start_is_one_line_and_keeps_the_status(run, tiny_fs, capsys):
    """tb/ on a file system of its own, full: the resume stops in one line that names that file
    system and tb/, before training, and the record of how the run last ended stays."""
    RunDir(run).write_status("interrupted", 250)
    mnt = tiny_fs("64k", at=RunDir(run).tb_dir)
    fill_fs(mnt)
    assert main(["train", "--out", run, "--resume", "--no-progress", "--logger", "csv,tensorboard"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"imssr: error: no space left on {mnt} while writing {mnt}"], err
    assert RunDir(run).read_status()["state"] == "interrupted"
    assert load_checkpoint(RunDir(run).latest).step == 250


def test_a_full_tensorboard_disk_during_the_run_keeps_a_finished_run_finished(run, tiny_fs, capsys):
    """tb/ (a file system of its own) fills while the run trains: one warning line that names it,
    TensorBoard stops, and the run reaches its budget, finished."""
    cfg = _cfg()
    cfg.train.tensorboard = True
    mnt = tiny_fs("1m", at=RunDir(run).tb_dir)
    t = Trainer(cfg, run, resume=True)
    try:
        t.begin()
        # The new event file's first page (tmpfs allocates 4 KiB pages) nearly full, then no free
        # page: the run's first events need one.
        (events,) = [os.path.join(mnt, name) for name in os.listdir(mnt)]
        while os.path.getsize(events) < 4096 - 200:
            t.logger.tb.add_scalar("padding", 0.0)
            t.logger.tb.flush()
        fill_fs(mnt)
        with RunDir(run).recording(lambda: t.step):
            t.train()
    finally:
        t.close()
    assert RunDir(run).read_status()["state"] == "finished"
    assert load_checkpoint(RunDir(run).latest).step == 375
    warnings = [line for line in capsys.readouterr().out.splitlines() if "TensorBoard" in line]
    assert warnings == [f"imssr: warning: no space left on {mnt} while writing {mnt}: TensorBoard stops here "
                        "(train.csv and eval.csv keep every row)"], warnings
    assert [int(r["step"]) for r in read_csv(RunDir(run).train_log)] == [125, 250, 375]


def test_a_file_size_limit_names_the_file_and_keeps_the_previous_checkpoint(tmp_path):
    """``ulimit -f`` (RLIMIT_FSIZE; Python ignores SIGXFSZ, so a write past it fails with EFBIG):
    one line naming the file and the limit, the previous checkpoint whole, no temporary file."""
    run = str(tmp_path / "run")
    code = (
        "import resource, sys, torch\n"
        f"sys.path.insert(0, {os.path.dirname(__file__)!r})\n"
        "from conftest import a_checkpoint\n"
        "from imssr.errors import ImssrError\n"
        "from imssr.rundir import RunDir\n"
        f"run = RunDir({run!r})\n"
        "run.save_checkpoint(a_checkpoint(step=1, agent={'w': torch.zeros(10)}))\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (1_000_000, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))\n"
        "try:\n"
        "    run.save_checkpoint(a_checkpoint(step=2, agent={'w': torch.zeros(1_000_000)}))\n"
        "except ImssrError as exc:\n"
        "    print(exc)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == (f"file larger than this process's file-size limit (ulimit -f: 1.0 MB) while "
                                   f"writing {RunDir(run).latest} (4.0 MB needed)")
    assert load_checkpoint(RunDir(run).latest).step == 1
    assert sorted(os.listdir(os.path.join(run, "checkpoints"))) == ["latest.pt", "step-000000001.pt"]


def test_an_evaluation_appended_after_a_torn_row_starts_on_a_line_of_its_own(tmp_path):
    """A row of evaluate.csv cut short by a full disk (or a kill) is dropped before the next
    evaluation appends: it used to continue the torn line ("240,30,tra240,30,training,...")."""
    from imssr.training.logger import append_locked

    path = tmp_path / "evaluate.csv"
    path.write_text("frame,step,mode\n240,30,training\n480,60,tra")
    append_locked(str(path), ["frame", "step", "mode"], [{"frame": 720, "step": 90, "mode": "training"}])
    assert path.read_text() == "frame,step,mode\n240,30,training\n720,90,training\n"
    torn_header = tmp_path / "evaluate_episodes.csv"
    torn_header.write_text("frame,st")
    append_locked(str(torn_header), ["frame", "step"], [{"frame": 1, "step": 2}])
    assert torn_header.read_text() == "frame,step\n1,2\n"


def test_a_lost_config_json_is_restored_from_the_checkpoint_and_the_resume_is_exact(run, full, capsys):
    """``--resume`` on a run whose config.json is gone: the checkpoint holds the config it was
    trained with, which is written back (one line says so), and the run ends as it would have."""
    os.unlink(os.path.join(run, "config.json"))
    assert main(["train", "--resume", "--out", run, "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert f"imssr: {run}/config.json was missing; restored from {RunDir(run).latest} (the config it was " \
           "trained with)" in out
    for name in ("train.csv", "eval.csv"):
        assert _strip(read_csv(os.path.join(run, name))) == _strip(read_csv(os.path.join(full[0], name))), name
    assert RunDir(run).read_config().to_dict() == RunDir(full[0]).read_config().to_dict()


def test_without_config_json_or_checkpoint_there_is_nothing_to_resume(tmp_path, capsys):
    os.makedirs(tmp_path / "run")
    assert main(["train", "--resume", "--out", str(tmp_path / "run")]) == 2
    assert f"nothing to resume: {tmp_path / 'run' / 'config.json'} does not exist" in capsys.readouterr().err


@contextlib.contextmanager
def read_only(directory):
    """``directory`` read-only: a read-only bind mount of it (root, whom a folder's mode does not
    stop), else its mode."""
    if os.geteuid() != 0:
        mode = os.stat(directory).st_mode
        os.chmod(directory, 0o555)
        try:
            yield
        finally:
            os.chmod(directory, mode)
        return
    proc = subprocess.run(["mount", "--bind", "-o", "ro", directory, directory], capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a folder read-only here: {proc.stderr.strip()}")
    try:
        yield
    finally:
        subprocess.run(["umount", "-l", directory], check=False)


def test_evaluate_on_a_read_only_run_refuses_before_it_evaluates(run, capsys):
    """A run that cannot take the evaluation's results is one line before any episode is played,
    not after the whole evaluation."""
    with read_only(run):
        assert main(["evaluate", "--run", run, "--episodes", "1"]) == 2
    out, err = capsys.readouterr()
    assert err.startswith(f"imssr: error: imssr evaluate cannot write its results to {run} (") and \
        err.endswith("): nothing was evaluated; evaluate a copy of the run in a folder you can write\n"), err
    assert "return" not in out and not os.path.exists(RunDir(run).evaluate_log)
