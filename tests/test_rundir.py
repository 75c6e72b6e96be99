"""RunDir: a run directory's layout, its checkpoints (which one, and the fallback), its status,
and the agent of a run at a checkpoint."""
from __future__ import annotations

import contextlib
import fcntl
import os
import struct
import threading

import numpy as np
import pytest
import torch

from conftest import a_checkpoint, assert_same_tensors, filled_buffer, tiny_config
from imssr.errors import ImssrError
from imssr.integrity import seal_zip
from imssr.replay import FrameReplayBuffer
from imssr.rundir import (CONFIG_FILE, DONE_FILE, EVAL_LOG, LATEST_CHECKPOINT, STATUS_FILE, TRAIN_LOG, RunDir, RunPath,
                          parse_run_path, run_path)
from imssr.rundir.checkpoint import CheckpointDamaged, load_checkpoint


def _damage(path: str) -> None:
    """Flip one byte in the middle of a file (its checksum no longer matches)."""
    with open(path, "r+b") as fh:
        fh.seek(os.path.getsize(path) // 2)
        byte = fh.read(1)
        fh.seek(-1, os.SEEK_CUR)
        fh.write(bytes([byte[0] ^ 0xFF]))


def _state(step: int, **extra):
    return a_checkpoint(step=step, frame=step * 8, agent={"w": torch.full((4,), float(step))}, **extra)


def test_layout(tmp_path):
    run = RunDir(tmp_path / "run")
    root = str(tmp_path / "run")
    assert run.config_path == os.path.join(root, CONFIG_FILE) == os.path.join(root, "config.json")
    assert (run.train_log, run.eval_log) == (os.path.join(root, TRAIN_LOG), os.path.join(root, EVAL_LOG))
    assert run.log("evaluate_episodes") == run.evaluate_episodes_log == os.path.join(root, "evaluate_episodes.csv")
    assert run.latest == os.path.join(root, "checkpoints", LATEST_CHECKPOINT)
    assert run.numbered(250) == os.path.join(root, "checkpoints", "step-000000250.pt")
    # The replay index's name, formatted in one place, and the frame files it names beside it.
    assert RunDir.replay_name(250) == "replay-000000250.npz"
    assert run.video_path("training.gif") == os.path.join(root, "videos", "training.gif")
    assert (run.analysis_dir, run.tb_dir) == (os.path.join(root, "analysis"), os.path.join(root, "tb"))
    assert (run.done_path, run.status_path) == (os.path.join(root, DONE_FILE), os.path.join(root, STATUS_FILE))
    assert os.fspath(run) == root
    with pytest.raises(ImssrError, match=f"^run directory not found: {root}$"):
        run.require()
    filled_buffer(60, size=8).save(run.replay_path("replay-000000250.npz"))
    assert run.replay_files("replay-000000250.npz") == [
        os.path.join(root, "checkpoints", "replay-000000250.npz"),
        os.path.join(root, "checkpoints", "replay-frames-000000000000-000000000062.npy")]


def test_save_keeps_the_newest_copies_and_only_the_replay_files_latest_names(tmp_path):
    run = RunDir(tmp_path)
    os.makedirs(run.checkpoint_dir)
    # A single-file replay buffer (imssr before frame files) and a killed write's leftover.
    for name in ("replay-000000001.npz", "replay-000000001.npz.frames.npy", ".tmp-left-by-a-kill"):
        (tmp_path / "checkpoints" / name).write_bytes(b"x")
    buf = filled_buffer(40, capacity=100, size=8)
    for step in (1, 2, 3):
        for _ in range(40):  # 40 frames per save: the third save wraps the ring of 100
            buf.add(np.zeros(1), 0.0, 1.0, np.full((3, 8, 8), step, np.uint8))
        run.save_checkpoint(_state(step, replay_file=RunDir.replay_name(step)), keep=2, replay=buf)
    assert run.checkpoint_steps() == [2, 3]
    # Saved: frames 0-80 (the fill's 41 and 40 more), 81-120, 121-160; live: the last 100 (61-160),
    # so the first file stays for its last 20 frames.
    assert sorted(os.listdir(run.checkpoint_dir)) == [
        "latest.pt", "replay-000000003.npz", "replay-frames-000000000000-000000000081.npy",
        "replay-frames-000000000081-000000000121.npy", "replay-frames-000000000121-000000000161.npy",
        "step-000000002.pt", "step-000000003.pt"]
    # Real copies: the numbered file of latest's step is equal to it, not the same file.
    assert load_checkpoint(run.numbered(3)).step == load_checkpoint(run.latest).step == 3
    assert os.stat(run.numbered(3)).st_ino != os.stat(run.latest).st_ino
    run.save_checkpoint(_state(4), keep=0)
    assert run.checkpoint_steps() == [2, 3] and not any(n.startswith("replay-") for n in os.listdir(run.checkpoint_dir))


def test_parse_run_path_reads_back_run_path():
    for args in (("/r", "walker_walk", "im-curl", 3, None), ("runs/x", "cartpole_swingup", "curl", 0, "0.05"),
                 ("", "t", "a", 12, "1e-05")):
        path = run_path(*args)
        assert parse_run_path(path) == RunPath(*args)
    assert parse_run_path(os.path.join("fp32", "t", "a", "seed_1")) == RunPath("fp32", "t", "a", 1, None)
    for path in ("seed_1", os.path.join("a", "seed_x"), os.path.join("t", "a", "run"), os.path.join("beta0_1", "seed_2")):
        assert parse_run_path(path) is None, path


def test_choosing_a_checkpoint_and_falling_back_to_a_valid_one(tmp_path):
    run = RunDir(tmp_path)
    with pytest.raises(ImssrError, match="^nothing to resume: .*latest.pt does not exist$"):
        run.checkpoint()
    assert not run.has_checkpoint()
    for step in (125, 250):
        run.save_checkpoint(_state(step), keep=2)
    state, path, note = run.checkpoint()
    assert (state.step, path, note) == (250, run.latest, None)
    # By step, by file name inside checkpoints/, by path.
    assert run.checkpoint("125").checkpoint.step == 125
    assert run.checkpoint("step-000000125.pt").checkpoint.step == 125
    assert run.checkpoint(run.numbered(250)).checkpoint.step == 250
    with pytest.raises(ImssrError, match="no checkpoint at agent step 99 .*; retained steps: 125, 250"):
        run.checkpoint("99")
    with pytest.raises(ImssrError, match="^checkpoint not found: nope.pt$"):
        run.checkpoint("nope.pt")
    # A damaged latest.pt: the newest numbered checkpoint that verifies, with a note.
    _damage(run.latest)
    _damage(run.numbered(250))
    state, path, note = run.checkpoint()
    assert (state.step, path) == (125, run.numbered(125))
    assert note == "latest.pt is damaged (checksum mismatch); resuming from step-000000125.pt at agent step 125"
    assert run.checkpoint(verb="evaluating").note.endswith("evaluating step-000000125.pt at agent step 125")
    # A named checkpoint is that one, damaged or not.
    with pytest.raises(CheckpointDamaged, match="checksum mismatch"):
        run.checkpoint("250")
    # latest.pt missing: a retained checkpoint still counts as something to resume.
    os.unlink(run.latest)
    assert run.has_checkpoint() and not run.has_latest()
    assert run.checkpoint().note.startswith("latest.pt is missing; resuming from step-000000125.pt")
    _damage(run.numbered(125))
    with pytest.raises(ImssrError, match="is missing, and no retained step-\\*.pt checkpoint in .* is valid"):
        run.checkpoint()


def test_a_checkpoint_reads_back_as_written_field_by_field(tmp_path):
    from dataclasses import fields

    from imssr.rundir.checkpoint import Checkpoint

    run = RunDir(tmp_path / "run")
    ckpt = _state(7, replay_file=None, episode_state={"return": 1.5}, torch_threads=2)
    run.save_checkpoint(ckpt)
    back = load_checkpoint(run.latest)
    assert isinstance(back, Checkpoint) and back.step == 7 and back.episode_state == {"return": 1.5}
    assert_same_tensors(back.to_state(), ckpt.to_state())
    # In the file: the fields' names in their order, then the format version.
    raw = torch.load(run.latest, weights_only=True)
    assert list(raw) == [f.name for f in fields(Checkpoint)] + ["format_version"]


def test_a_file_that_lacks_a_field_of_a_checkpoint_is_one_line(tmp_path):
    path = str(tmp_path / "x.pt")
    state = _state(3).to_state()
    del state["agent"], state["step"]
    torch.save(dict(state, format_version=1), path)
    seal_zip(path)
    with pytest.raises(CheckpointDamaged, match=r"^\S+x\.pt is not a whole imssr checkpoint: it holds no agent, step$"):
        load_checkpoint(path)


def test_a_failed_save_keeps_the_replay_files_latest_names_and_drops_its_own(tmp_path, monkeypatch):
    """A full disk while writing latest.pt: the previous latest.pt and its replay files stay, the
    replay files this save wrote go (no checkpoint names them)."""
    run = RunDir(tmp_path / "run")
    buf = filled_buffer(40, capacity=100, size=8)
    run.save_checkpoint(_state(1, replay_file=RunDir.replay_name(1)), replay=buf)
    kept = sorted(os.listdir(run.checkpoint_dir))
    for _ in range(40):
        buf.add(np.zeros(1), 0.0, 1.0, np.full((3, 8, 8), 2, np.uint8))

    def full_disk(*args, **kwargs):
        raise ImssrError("no space left on device while writing latest.pt")

    import imssr.rundir.checkpoint as checkpoint_file

    monkeypatch.setattr(checkpoint_file, "write_checkpoint", full_disk)
    with pytest.raises(ImssrError, match="no space left"):
        run.save_checkpoint(_state(2, replay_file=RunDir.replay_name(2)), replay=buf)
    assert sorted(os.listdir(run.checkpoint_dir)) == kept and load_checkpoint(run.latest).step == 1


def test_status_transitions(tmp_path):
    run = RunDir(tmp_path / "run")
    assert run.status() == "new"
    lock = run.open()
    try:
        assert run.status() == "running"  # whatever it recorded before
    finally:
        lock.release()
    assert run.status() == "new"
    run.save_checkpoint(_state(5), keep=1)
    assert run.status() == "interrupted"  # a checkpoint and no record: killed outright
    for ending in ("failed", "diverged", "interrupted", "finished"):
        run.write_status(ending, step=5, error="imssr: error: something")
        assert run.status() == ending and run.read_status()["step"] == 5
    with pytest.raises(ValueError):
        run.write_status("running")
    # Taking the run keeps the record of the last training; one that starts drops it.
    run.write_status("failed", step=5)
    run.open().release()
    assert run.status() == "failed"
    lock = run.open()
    try:
        with run.recording(lambda: 5):
            assert run.read_status() is None
    finally:
        lock.release()
    assert run.read_status()["state"] == "finished"
    os.unlink(run.status_path)
    assert run.status() == "interrupted"
    # A sweep's done marker: finished (with a budget), whatever a torn record says.
    (tmp_path / "run" / STATUS_FILE).write_text('{"state": "fail')
    run.write_done(250, 250, attempt=1, resumed=False)
    assert run.status() == "finished" and run.is_done(250) and not run.is_done(251)
    assert run.done_steps() == 250


def test_a_status_probe_does_not_turn_a_starting_writer_away(tmp_path):
    """RunDir.in_use() holds a shared lock for an instant; a writer that starts in that instant
    waits for it instead of calling the run busy. A real writer still turns it away."""
    run = RunDir(tmp_path / "run")
    os.makedirs(run.path)
    with open(run.lock_path, "w") as fh:  # what a writer killed with -9 leaves: a file, no lock
        fh.write("999999 elsewhere\n")
    assert not run.in_use()
    probe = os.open(run.lock_path, os.O_RDONLY)
    fcntl.flock(probe, fcntl.LOCK_SH | fcntl.LOCK_NB)  # as in_use() does, between open and close
    threading.Timer(0.05, os.close, (probe,)).start()
    lock = run.open()  # acquired once the probe lets go
    try:
        assert run.in_use() and run.status() == "running"
        with pytest.raises(ImssrError, match="is in use by PID"):
            RunDir(tmp_path / "run").open()
    finally:
        lock.release()
    assert not run.in_use()


def test_progress_comes_from_the_last_complete_rows(tmp_path):
    run = RunDir(tmp_path)
    assert (run.last_evaluation(), run.trained_steps()) == ((0, 0), 0)
    (tmp_path / "eval.csv").write_text("frame,step,mode\n1000,125,training\n2000,250,training\n30")
    (tmp_path / "train.csv").write_text("frame,step\n1000,125\n" + "".join(f"{8 * s},{s}\n" for s in range(126, 900)))
    assert run.last_evaluation() == (250, 2000) and run.trained_steps() == 899


def test_load_agent_builds_the_run_at_its_checkpoint_and_refuses_a_mismatch(tmp_path):
    from imssr.training.build import build_agent, load_agent

    cfg = tiny_config("curl")
    run = RunDir(tmp_path / "run")
    run.write_config(cfg)
    shape = (9, cfg.env.image_size, cfg.env.image_size)
    trained = build_agent(cfg, shape, 1, "cpu")
    with torch.no_grad():
        for p in trained.nets.parameters():
            p.add_(0.5)
    run.save_checkpoint(a_checkpoint(step=125, frame=1000, agent=trained.state_dict()))
    loaded = load_agent(run, device="cpu")
    assert (loaded.step, loaded.frame, loaded.note, loaded.obs_shape) == (125, 1000, None, shape)
    obs = np.random.default_rng(0).integers(0, 255, shape, dtype=np.uint8)
    assert np.array_equal(loaded.agent.act(obs, True), trained.act(obs, True))
    # The checkpoint of another architecture than config.json describes: one line.
    cfg.agent.hidden_dim = 64
    run.write_config(cfg)
    with pytest.raises(ImssrError, match="^checkpoint does not match the run's config: "):
        load_agent(run, device="cpu")
    with pytest.raises(ImssrError, match="^run directory not found"):
        load_agent(RunDir(tmp_path / "none"))


def test_recording_says_how_a_training_ended(tmp_path):
    from imssr.errors import DivergedError

    class Stopped(Exception):
        pass

    run = RunDir(tmp_path)
    cases = [(None, "finished"), (Stopped("stopped at agent step 7 by SIGTERM"), "interrupted"),
             (KeyboardInterrupt(), "interrupted"), (DivergedError("diverged at agent step 7: critic loss nan"),
                                                    "diverged"), (ImssrError("no space left\nmore"), "failed")]
    for exc, state in cases:
        with pytest.raises(type(exc)) if exc else contextlib.nullcontext():
            with run.recording(lambda: 7, interrupted=(Stopped,)):
                if exc:
                    raise exc
        record = run.read_status()
        assert (record["state"], record["step"], run.status()) == (state, 7, state)
        assert record["error"] == ("" if exc is None else (str(exc).splitlines() or ["KeyboardInterrupt"])[0])



def _flip_weight_and_cut_the_last_byte(path: str) -> None:
    """The issue's damage: one byte of a weight flipped and the file's last byte cut (a zip
    reader still opens it; only the seal, no longer at the end, tells)."""
    data = bytearray(open(path, "rb").read())
    at = data.find(struct.pack("<f", 250.0) * 4)
    assert at > 0
    data[at] ^= 0x01
    with open(path, "wb") as fh:
        fh.write(bytes(data[:-1]))


def _append_a_byte(path: str) -> None:
    with open(path, "ab") as fh:
        fh.write(b"\0")


def _unseal(path: str) -> None:
    """The same checkpoint, whole, as ``torch.save`` alone writes it: no seal."""
    torch.save(dict(load_checkpoint(path).to_state(), format_version=1), path)


CUT_OR_EXTENDED = "its checksum is not at its end: cut short or extended"


@pytest.mark.parametrize("damage, reason", [(_flip_weight_and_cut_the_last_byte, CUT_OR_EXTENDED),
                                            (_append_a_byte, CUT_OR_EXTENDED),
                                            (_unseal, "not an imssr checkpoint")])
def test_a_checkpoint_that_cannot_be_verified_is_refused_and_a_valid_one_offered(tmp_path, damage, reason):
    run = RunDir(tmp_path / "run")
    for step in (125, 250):
        run.save_checkpoint(_state(step), keep=2)
    damage(run.latest)
    with pytest.raises(CheckpointDamaged) as err:
        load_checkpoint(run.latest)
    assert err.value.reason == reason and run.latest in str(err.value)
    # Unnamed: the newest retained checkpoint that verifies, said in one line.
    state, path, note = run.checkpoint()
    assert (state.step, path) == (250, run.numbered(250))
    assert note == f"latest.pt is damaged ({reason}); resuming from step-000000250.pt at agent step 250"
    # Named: refused, in one line that names the newest retained one that verifies and how to take it.
    damage(run.numbered(250))
    for spec in ("250", run.latest):
        with pytest.raises(CheckpointDamaged, match=r"; step-000000125\.pt verifies \(agent step 125: "
                                                    r"--checkpoint 125\)$"):
            run.checkpoint(spec)


def test_a_named_checkpoint_outside_the_run_offers_none_of_its_checkpoints(tmp_path):
    run = RunDir(tmp_path / "run")
    run.save_checkpoint(_state(125), keep=1)
    elsewhere = str(tmp_path / "other.pt")
    torch.save({"format_version": 1}, elsewhere)
    with pytest.raises(CheckpointDamaged, match=r"^\S+other\.pt is not an imssr checkpoint: it carries no imssr "
                                                r"checksum$"):
        run.checkpoint(elsewhere)


def _cut_in_half(path: str) -> None:
    data = open(path, "rb").read()
    with open(path, "wb") as fh:
        fh.write(data[:len(data) // 2])


@pytest.mark.parametrize("fault", [_cut_in_half, os.unlink, _damage])
def test_a_cleanup_that_cannot_read_the_replay_index_removes_nothing(tmp_path, capsys, fault):
    """What is live is what the index names: an index that cannot be read and verified names
    nothing for sure, so no frame file goes (the next save cleans up)."""
    run = RunDir(tmp_path / "run")
    buf = filled_buffer(40, capacity=100, size=8)
    name = RunDir.replay_name(1)
    run.save_checkpoint(_state(1, replay_file=name), replay=buf)
    (tmp_path / "run" / "checkpoints" / "replay-frames-000000000000-000000000007.npy").write_bytes(b"old")
    files = sorted(os.listdir(run.checkpoint_dir))
    fault(run.replay_path(name))
    run.remove_unnamed_replay_files(name)
    after = sorted(os.listdir(run.checkpoint_dir))
    assert after == [f for f in files if f != name or fault is not os.unlink]
    (line,) = capsys.readouterr().out.splitlines()
    assert line.startswith("imssr: warning: ") and run.replay_path(name) in line
    assert line.endswith("; no replay file is removed")


def test_a_failed_save_of_a_run_that_has_read_no_replay_keeps_latests_replay_files(tmp_path, monkeypatch):
    """A process that did not load latest.pt's replay buffer (a resume that refills it) and fails
    to save removes only the files its own save wrote, not latest.pt's."""
    path = tmp_path / "run"
    RunDir(path).save_checkpoint(_state(1, replay_file=RunDir.replay_name(1)),
                                 replay=filled_buffer(40, capacity=100, size=8))
    kept = sorted(os.listdir(RunDir(path).checkpoint_dir))

    def full_disk(*args, **kwargs):
        raise ImssrError("no space left on device while writing latest.pt")

    import imssr.rundir.checkpoint as checkpoint_file

    monkeypatch.setattr(checkpoint_file, "write_checkpoint", full_disk)
    with pytest.raises(ImssrError, match="no space left"):
        RunDir(path).save_checkpoint(_state(2, replay_file=RunDir.replay_name(2)),
                                     replay=filled_buffer(30, capacity=100, size=8, seed=1))
    monkeypatch.undo()
    assert sorted(os.listdir(RunDir(path).checkpoint_dir)) == kept
    FrameReplayBuffer(100, (3, 8, 8), 1).load(RunDir(path).replay_path(RunDir.replay_name(1)))


def test_a_run_directory_as_imssr_writes_it_reads_back(tmp_path):
    """The files of a run, written here without RunDir under the names and in the forms imssr
    has always written them, are what RunDir reads: the on-disk layout is a contract with every
    run directory already written, whatever shape the code that reads it takes."""
    import json

    from imssr.rundir import batch_checkpoints
    from imssr.rundir.checkpoint import write_checkpoint

    root = tmp_path / "run"
    (root / "checkpoints").mkdir(parents=True)
    cfg = tiny_config("curl")
    (root / "config.json").write_text(cfg.to_json() + "\n")
    (root / "provenance.json").write_text(json.dumps({"records": [{"version": "0.1"}]}))
    (root / "train.csv").write_text("frame,step,episode\n800,100,1\n2000,250,2\n")
    (root / "eval.csv").write_text("frame,step,mode\n2000,250,training\n")
    (root / "status.json").write_text(json.dumps({"state": "interrupted", "step": 250, "error": "stopped",
                                                  "time": "2026-01-01T00:00:00"}))
    buf = filled_buffer(40, capacity=100, size=8)
    buf.save(str(root / "checkpoints" / "replay-000000250.npz"))
    for name, step in (("step-000000125.pt", 125), ("step-000000250.pt", 250), ("latest.pt", 250)):
        replay = "replay-000000250.npz" if step == 250 else None
        write_checkpoint(str(root / "checkpoints" / name),
                         _state(step, replay_file=replay, replay_state=buf.state_dict() if replay else None))
    run = RunDir(str(root))
    assert (run.status(), run.outcome()) == ("interrupted", ("interrupted", ""))
    assert run.read_config().to_dict() == cfg.to_dict() and run.read_provenance() == [{"version": "0.1"}]
    assert (run.trained_steps(), run.last_evaluation(), run.checkpoint_steps()) == (250, (250, 2000), [125, 250])
    found = run.checkpoint()
    assert (found.checkpoint.step, found.path, found.note) == (250, str(root / "checkpoints" / "latest.pt"), None)
    loaded = FrameReplayBuffer(100, (3, 8, 8), 1)
    assert run.load_replay(found, loaded) is None and loaded.state_dict() == buf.state_dict()
    assert np.array_equal(loaded.frames, buf.frames)
    assert run.checkpoint("125").checkpoint.step == 125
    assert run.load_replay(run.checkpoint("125"), loaded) == "checkpoint holds no replay buffer"
    (batch,) = batch_checkpoints([run], budget=500)
    assert (batch.checkpoint.step, batch.path) == (250, run.latest)
    assert run.run_parts() == [os.path.join("checkpoints", name) for name in
                               ("latest.pt", "step-000000125.pt", "step-000000250.pt", "replay-000000250.npz",
                                "replay-frames-000000000000-000000000041.npy")] + ["train.csv", "eval.csv"]
    (root / "done.json").write_text(json.dumps({"steps": 250, "frames": 2000}))
    os.unlink(root / "status.json")
    assert (run.status(), run.done_steps(), run.is_done(250), run.is_done(251)) == ("finished", 250, True, False)
    # What RunDir writes is read back by the same names and fields.
    run.write_status("failed", step=250, error="boom")
    run.write_done(250, 250, attempt=2, resumed=True)
    run.record_provenance({"version": "0.2"})
    assert set(json.loads((root / "status.json").read_text())) == {"state", "step", "error", "time"}
    assert set(json.loads((root / "done.json").read_text())) == {
        "steps", "frames", "final_step", "final_frame", "evaluations", "attempt", "resumed", "seconds", "finished"}
    assert json.loads((root / "provenance.json").read_text()) == {"records": [{"version": "0.1"}, {"version": "0.2"}]}
