"""Files someone else wrote (a shared file system): a checkpoint or replay file that would run
code when unpickled is refused in one line, and the code never runs; a file that is no
checkpoint or no log is one line; a link planted in a run directory is not written through."""
from __future__ import annotations

import io
import os
import pickle
import re
import zipfile

import numpy as np
import pytest
import torch

from conftest import a_checkpoint, tiny_config, train_run
from imssr.cli import main
from imssr.errors import ImssrError
from imssr.files import atomic_write_text
from imssr.integrity import seal_zip
from imssr.replay import FrameReplayBuffer
from imssr.replay.buffer import ReplayFileError
from imssr.rundir import RunDir
from imssr.rundir.checkpoint import load_checkpoint


class Evil:
    """Unpickling it runs a shell command that creates ``marker``."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


@pytest.fixture
def run(tmp_path):
    """A run directory with its config (all `imssr evaluate` / `--resume` read before a checkpoint)."""
    path = tmp_path / "run"
    atomic_write_text(str(path / "config.json"), tiny_config("curl").to_json() + "\n")
    return str(path)


def _one_error_line(err):
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("imssr: error: "), err
    return lines[0]


def test_an_evil_checkpoint_is_refused_and_runs_nothing(run, tmp_path, capsys):
    marker = tmp_path / "PWNED"
    evil = str(tmp_path / "evil.pt")
    torch.save({"format_version": 1, "x": Evil(marker)}, evil)
    assert main(["evaluate", "--run", run, "--checkpoint", evil]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert line == f"imssr: error: {evil} is not an imssr checkpoint: it contains objects of type os.system"
    assert not marker.exists()
    # The same file as the run's latest.pt: --resume refuses it too.
    os.makedirs(os.path.dirname(RunDir(run).latest))
    os.replace(evil, RunDir(run).latest)
    assert main(["train", "--out", run, "--resume", "--no-progress"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert line.endswith("latest.pt is not an imssr checkpoint: it contains objects of type os.system")
    assert not marker.exists()


def test_a_checkpoint_with_a_class_of_its_own_is_refused(tmp_path):
    path = str(tmp_path / "odd.pt")
    torch.save({"format_version": 1, "x": Evil("/nonexistent/x"), "y": FrameReplayBuffer}, path)
    with pytest.raises(Exception, match=r"it contains objects of type imssr\.replay\.buffer\.FrameReplayBuffer, "
                                        r"os\.system$"):
        load_checkpoint(path)


def test_imssr_checkpoints_hold_only_tensors_and_plain_values(tmp_path):
    """What the trainer saves (numpy RNG states included) needs no allow-listed numpy type."""
    from imssr.rng import rng_states

    run = str(tmp_path / "run")
    RunDir(run).save_checkpoint(a_checkpoint(step=1, global_rng=rng_states()))
    assert torch.serialization.get_unsafe_globals_in_checkpoint(RunDir(run).latest) == []
    assert load_checkpoint(RunDir(run).latest).global_rng["numpy"]["bit_generator"] == "MT19937"


def test_a_replay_file_with_pickled_objects_is_refused(tmp_path):
    marker = tmp_path / "PWNED"
    path = str(tmp_path / "replay.npz")
    np.savez(path, meta=np.array([Evil(marker)], dtype=object), actions=np.zeros((2, 1), np.float32))
    np.save(path + ".frames.npy", np.zeros((2, 3, 8, 8), np.uint8))
    with pytest.raises(ReplayFileError, match=r"^\S+replay\.npz is not a replay buffer imssr wrote: it carries "
                                              r"no imssr checksum$"):
        FrameReplayBuffer(10, (3, 8, 8), 1).load(path)
    seal_zip(path)  # a seal is no signature: anyone can write one, and the arrays are still refused
    with pytest.raises(ReplayFileError, match=r"^corrupt replay buffer file .*Object arrays cannot be loaded"):
        FrameReplayBuffer(10, (3, 8, 8), 1).load(path)
    assert not marker.exists()


# -- files that are not what their names say ------------------------------------------------

@pytest.mark.parametrize("content", [b"hello world\n", None])
def test_a_file_that_is_no_checkpoint_is_one_line(run, tmp_path, capsys, content):
    """Text, or /etc/passwd, given as a checkpoint: torch's reader of files that are no zip
    archive would fail with a KeyError or IndexError."""
    path = str(tmp_path / "latest.pt")
    if content is None:
        path = "/etc/passwd"
    else:
        with open(path, "wb") as fh:
            fh.write(content)
    with pytest.raises(ImssrError, match=rf"^{path} is not an imssr checkpoint \(not a torch checkpoint file\)$"):
        load_checkpoint(path)
    assert main(["evaluate", "--run", run, "--checkpoint", path, "--episodes", "1"]) == 2
    assert _one_error_line(capsys.readouterr().err) == \
        f"imssr: error: {path} is not an imssr checkpoint (not a torch checkpoint file)"


def test_text_in_latest_falls_back_to_the_newest_valid_step_file(tmp_path):
    run = RunDir(str(tmp_path / "run"))
    run.save_checkpoint(a_checkpoint(step=5), keep=2)
    run.save_checkpoint(a_checkpoint(step=9), keep=2)
    with open(run.latest, "w") as fh:
        fh.write("hello world\n")
    state, path, note = run.checkpoint()
    assert (state.step, path) == (9, run.numbered(9))
    assert note == ("latest.pt is damaged (not an imssr checkpoint); resuming from step-000000009.pt "
                    "at agent step 9")


@pytest.mark.parametrize("rows", [
    "frame,step,mode,return_mean,return_std\n1000,125,training,5.0,1.0\n2000,250\n",  # a short row
    "frame,step,mode,return_mean,return_std\n1000,abc,training,5.0,1.0\n",  # not a number
    "frame,step\n1000,125\n",  # columns missing
])
def test_plot_of_a_malformed_eval_csv_is_one_line(run, capsys, rows):
    with open(RunDir(run).eval_log, "w") as fh:
        fh.write(rows)
    assert main(["plot", "--run", run]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert line.startswith("imssr: error: row ") and f"of {RunDir(run).eval_log} is not an evaluation row" in line


def test_plot_leaves_out_a_last_row_cut_short_by_a_killed_writer(run, capsys):
    """A training killed mid-write leaves "...,training,2." of 2.5: the plot, like the report,
    draws the complete rows only."""
    with open(RunDir(run).eval_log, "w") as fh:
        fh.write("frame,step,mode,return_mean,return_std\n1000,125,training,5.0,1.0\n2000,250,training,2.")
    assert main(["plot", "--run", run]) == 0
    assert os.path.getsize(RunDir(run).learning_curve_path) > 0


# -- links planted in a run directory --------------------------------------------------------

def test_writes_in_a_run_directory_refuse_to_follow_a_link(tmp_path):
    """A CSV log, `imssr evaluate`'s log, the sweep's log and the run's lock file: a symbolic link
    in their place (to someone's file outside the run) is refused in one line, and the file it
    points to is untouched."""
    from imssr.sweep.runner import execute_runs
    from imssr.training.logger import CSVLog, append_locked

    outside = tmp_path / "outside.csv"
    outside.write_text("precious\n")
    run = RunDir(str(tmp_path / "run"))
    os.makedirs(run.path)
    for path in (run.train_log, run.evaluate_log, run.sweep_log, run.lock_path):
        os.symlink(outside, path)
    message = r"^{} is a symbolic link; imssr writes only to a file of its own there \(remove the link\)$"
    with pytest.raises(ImssrError, match=message.format(run.train_log)):
        CSVLog(run.train_log, ["frame"]).write({"frame": 1})
    with pytest.raises(ImssrError, match=message.format(run.evaluate_log)):
        append_locked(run.evaluate_log, ["frame"], [{"frame": 1}])
    result = execute_runs([run.path], 10, 1)[0]
    assert not result["ok"] and result["returncode"] is None
    assert re.match(message.format(run.sweep_log), result["error"])
    with pytest.raises(ImssrError, match=message.format(run.lock_path)):
        run.open()
    assert outside.read_text() == "precious\n"


def test_a_provenance_json_that_is_a_link_is_refused_before_the_run_starts(tmp_path):
    """provenance.json is read back and rewritten whole at every start: a link in its place (to
    someone's file outside the run) is refused in one line before anything is written, rather
    than its target read into the run's records or the link set aside for a new list."""
    from imssr.training import Trainer

    outside = tmp_path / "notes.txt"
    outside.write_text("precious, not JSON\n")
    run = RunDir(str(tmp_path / "run"))
    os.makedirs(run.path)
    os.symlink(outside, run.provenance_path)
    message = r"^{} is a symbolic link; imssr writes only to a file of its own there \(remove the link\)$"
    with pytest.raises(ImssrError, match=message.format(run.provenance_path)):
        Trainer(tiny_config("curl"), run.path)
    assert not os.path.exists(run.config_path) and os.path.islink(run.provenance_path)
    with pytest.raises(ImssrError, match=message.format(run.provenance_path)):
        run.record_provenance({"event": "start"})
    assert os.listdir(run.path) == ["provenance.json"]
    assert outside.read_text() == "precious, not JSON\n"


# -- bytes that are not UTF-8, JSON nested too deep -----------------------------------------

def test_a_run_with_a_damaged_eval_log_is_skipped_by_report_and_export_with_a_note(tmp_path):
    from conftest import curve, make_run
    from imssr.report.export import export_runs
    from imssr.report.report import write_report

    root = str(tmp_path / "sweep")
    make_run(root, "curl", 1, curve(0, 0, 100))
    bad = make_run(root, "curl", 2, curve(0, 0, 200))
    with open(os.path.join(bad, "eval.csv"), "ab") as fh:
        fh.write(b"8000,1000,training,\xff\n")
    write_report(root, str(tmp_path / "report"), reps=20)
    md = open(tmp_path / "report" / "report.md").read()
    assert "curl/seed_2: " in md and "eval.csv is damaged: not UTF-8 text (byte 0xff at offset" in md
    assert "1 run, 4 evaluations." in md
    export_runs(root, str(tmp_path / "dest"))  # no traceback: the damaged run is not read


def test_a_damaged_train_log_stops_a_resume_in_one_line_naming_it(tmp_path, capsys):
    run = str(tmp_path / "run")
    cfg = tiny_config("curl", steps=130, eval_every_steps=130, eval_episodes=1)
    train_run(cfg, run, stop_at=70)
    with open(os.path.join(run, "train.csv"), "ab") as fh:
        fh.write(b"\xfe\xff")
    assert main(["train", "--resume", "--out", run, "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"imssr: error: {run}/train.csv is damaged: not UTF-8 text"), err


@pytest.mark.parametrize("what", ["config", "sweep"])
def test_json_nested_too_deep_is_one_line(tmp_path, capsys, what):
    path = tmp_path / f"{what}.json"
    path.write_text("[" * 100_000 + "]" * 100_000)
    args = ["train", "--config", str(path), "--out", str(tmp_path / "r")] if what == "config" else \
        ["sweep", "--file", str(path), "--dry-run"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nests its JSON too deeply" in err[0], err


def _zip_checkpoint() -> bytes:
    """The bytes torch writes for a small dict: a zip archive without a seal."""
    buf = io.BytesIO()
    torch.save({"format_version": 1}, buf)
    return buf.getvalue()


@pytest.mark.parametrize("sealed", [False, True])
def test_a_pickle_and_zip_polyglot_is_not_an_imssr_checkpoint(tmp_path, sealed):
    """A pickle with a zip archive behind it: a zip reader finds the archive, torch reads the
    pickle in its legacy format.  A seal is no signature (anyone can write one), so neither a
    sealed one nor an unsealed one is read, and the pickle never runs."""
    marker = tmp_path / "PWNED"
    path = str(tmp_path / "poly.pt")
    with open(path, "wb") as fh:
        fh.write(pickle.dumps(Evil(marker)) + _zip_checkpoint())
    if sealed:
        seal_zip(path)
    with pytest.raises(ImssrError, match=rf"^{path} is not an imssr checkpoint \(not a torch checkpoint file\)$"):
        load_checkpoint(path)
    assert not marker.exists()


def test_a_sealed_checkpoint_that_torch_refuses_is_not_an_imssr_checkpoint(tmp_path):
    """Bytes that match their seal are as written: what a weights-only load refuses in them is not
    damage, and torch's advice to load it with weights_only=False is not passed on."""
    path = str(tmp_path / "odd.pt")
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("archive/data.pkl", b"\x80\x02}(U\x01aK\x01u}b.")  # BUILD on a dict
        archive.writestr("archive/version", "3\n")
    seal_zip(path)
    with pytest.raises(ImssrError, match=rf"^{path} is not an imssr checkpoint: a weights-only load refuses it "
                                         r"\(Can only build .*\)$") as err:
        load_checkpoint(path)
    assert "weights_only" not in str(err.value)


@pytest.mark.parametrize("damage", ["flip a weight and cut the last byte", "no seal"])
def test_a_resume_from_a_checkpoint_that_cannot_be_verified_is_one_line(run, capsys, damage):
    """No retained copy to fall back to: the resume stops, naming the file, before anything trains."""
    weight = torch.arange(64, dtype=torch.float32)
    RunDir(run).save_checkpoint(a_checkpoint(step=5, agent={"w": weight}), keep=0)
    path = RunDir(run).latest
    if damage == "no seal":
        torch.save(dict(load_checkpoint(path).to_state(), format_version=1), path)
        expected = f"{path} is not an imssr checkpoint: it carries no imssr checksum"
    else:
        data = bytearray(open(path, "rb").read())
        data[data.find(weight.numpy().tobytes()) + 9] ^= 0x01
        with open(path, "wb") as fh:
            fh.write(bytes(data[:-1]))
        expected = f"checkpoint {path} is damaged (its checksum is not at its end: cut short or extended)"
    assert main(["train", "--out", run, "--resume", "--no-progress"]) == 2
    assert _one_error_line(capsys.readouterr().err) == f"imssr: error: {expected}"
