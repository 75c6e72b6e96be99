"""Every run says which code and machine made it: a provenance record at its start and at every
resume, kept by an export, shown per row by a report, with a warning where a row mixes them."""
import glob
import json
import os
import shutil
import socket
import subprocess
import sys

import pytest

from conftest import REPO, curve, image_folder, make_run, tiny_config, train_run
from imssr.errors import ImssrError
from imssr.provenance import FIELDS, SOURCE_STAMP, command_line, git_state, record, summary, write_stamp
from imssr.report.export import export_runs
from imssr.report.report import write_report
from imssr.rundir import RunDir


def _cfg():
    cfg = tiny_config("curl")
    cfg.train.steps, cfg.train.eval_every_steps, cfg.train.eval_episodes = 130, 130, 1
    return cfg


def test_a_run_records_its_start_and_every_resume(tmp_path):
    run = str(tmp_path / "run")
    train_run(_cfg(), run, stop_at=70)
    train_run(_cfg(), run, resume=True)
    records = RunDir(run).read_provenance()
    assert [(r["event"], r["agent_step"]) for r in records] == [("start", 0), ("resume", 70)]
    first = records[0]
    assert set(FIELDS) <= set(first) and first["device"] == "cpu" and first["torch"]
    assert first["cpu"] and first["device_name"] == first["cpu"] and isinstance(first["cpu_native_bf16"], (bool, type(None)))
    if os.path.exists(os.path.join(REPO, ".git")):  # from a checkout: its commit and whether it is modified
        assert len(first["git_commit"]) == 40 and isinstance(first["git_clean"], bool)
    text = open(RunDir(run).provenance_path).read()
    assert socket.gethostname() not in text and os.path.expanduser("~") not in text


def test_the_command_line_keeps_no_paths_of_the_machine():
    home = os.path.expanduser("~")
    argv = ["/opt/venv/bin/imssr", "train", "--out", "/scratch/alice/runs/x", "--config=/home/a/c.json",
            "--task", "walker_walk", "--out", "runs/rel", f"{home}/data"]
    assert command_line(argv) == ["imssr", "train", "--out", "…/x", "--config=…/c.json", "--task", "walker_walk",
                                  "--out", "runs/rel", "…/data"]


def test_paths_inside_set_values_are_cut_too():
    argv = ["imssr", "train", "--set", "aux.image_dir=/home/me/images", "--set", "k=[/a/b,~/c/d/,rel/e]",
            "--set=env.footage_dir=~/clips/v.mp4", "--set", "w=(/p/q)", "--set", "train.device=cuda:0",
            "--set", "k=a/b"]
    assert command_line(argv) == ["imssr", "train", "--set", "aux.image_dir=…/images", "--set", "k=[…/b,…/d,rel/e]",
                                  "--set=env.footage_dir=…/v.mp4", "--set", "w=(…/q)", "--set", "train.device=cuda:0",
                                  "--set", "k=a/b"]


def test_an_exported_provenance_keeps_no_absolute_path_of_a_set_value(tmp_path, monkeypatch):
    from imssr.cli import main

    footage, config = tmp_path / "my_clips", tmp_path / "tiny.json"
    footage.mkdir()
    cfg = _cfg()
    cfg.train.steps, cfg.train.seed_steps, cfg.train.eval_every_steps, cfg.train.checkpoint_every_steps = 20, 10, 20, 20
    cfg.train.torch_threads = 1
    config.write_text(json.dumps(cfg.to_dict()))
    run = tmp_path / "sweep" / "cartpole_swingup_sparse" / "curl" / "seed_0"
    argv = ["imssr", "train", "--config", str(config), "--set", f"env.footage_dir={footage}", "--no-progress",
            "--out", str(run)]
    monkeypatch.setattr(sys, "argv", argv)  # what provenance.record reads, as in an `imssr train` process
    assert main(argv[1:]) == 0
    assert export_runs(str(tmp_path / "sweep"), str(tmp_path / "dest"))[0].state == "new"
    (exported,) = glob.glob(str(tmp_path / "dest" / "**" / "provenance.json"), recursive=True)
    for path in (run / "provenance.json", exported):
        assert str(tmp_path) not in open(path).read()
        (record,) = json.load(open(path))["records"]
        assert record["command"] == ["imssr", "train", "--config", "…/tiny.json", "--set", "env.footage_dir=…/my_clips",
                                     "--no-progress", "--out", "…/seed_0"]


def test_an_installed_package_has_no_git_state(monkeypatch, tmp_path):
    import imssr.provenance as prov

    git_state.cache_clear()
    monkeypatch.setattr(prov, "__file__", str(tmp_path / "site-packages" / "imssr" / "provenance.py"))
    try:
        assert git_state() == (None, None)
        assert record(__import__("torch").device("cpu"), "start", 0, ["imssr"])["git_commit"] is None
    finally:
        git_state.cache_clear()


def _git(repo, *args):
    return subprocess.run(["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t", *args],
                          capture_output=True, text=True, check=True).stdout.strip()


def _state_of(monkeypatch, top):
    """git_state() of imssr imported from the folder ``top``."""
    import imssr.provenance as prov

    monkeypatch.setattr(prov, "__file__", str(top / "imssr" / "provenance.py"))
    git_state.cache_clear()
    return git_state()


def test_a_copy_without_git_takes_its_commit_from_its_source_stamp(monkeypatch, tmp_path):
    repo, copy = tmp_path / "repo", tmp_path / "copy"
    (repo / "imssr").mkdir(parents=True)
    (repo / "imssr" / "__init__.py").write_text("")
    (repo / "imssr" / "agent.py").write_text("LR = 1e-3\n")
    (repo / "README.md").write_text("docs\n")
    _git(tmp_path, "init", "-q", str(repo))
    _git(repo, "add", ".")
    _git(repo, "commit", "-q", "-m", "start")
    commit = _git(repo, "rev-parse", "HEAD")
    try:
        assert write_stamp(str(repo)) == str(repo / SOURCE_STAMP)
        shutil.copytree(repo, copy, ignore=shutil.ignore_patterns(".git"))
        assert _state_of(monkeypatch, copy) == (commit, True)
        assert record(__import__("torch").device("cpu"), "start", 0, ["imssr"])["git_commit"] == commit
        (copy / "README.md").write_text("other docs\n")  # not the package's: still its code
        assert _state_of(monkeypatch, copy) == (commit, True)
        (copy / "imssr" / "agent.py").write_text("LR = 2e-3\n")
        assert _state_of(monkeypatch, copy) == (commit, False)
        (copy / "imssr" / "agent.py").write_text("LR = 1e-3\n")
        (copy / "imssr" / "extra.py").write_text("")  # a module the commit does not have
        assert _state_of(monkeypatch, copy) == (commit, False)
        os.unlink(copy / "imssr" / "extra.py")
        os.unlink(copy / "imssr" / "agent.py")
        assert _state_of(monkeypatch, copy) == (commit, False)
        (copy / SOURCE_STAMP).write_text("{not json")
        assert _state_of(monkeypatch, copy) == (None, None)
        # Stamped in a checkout with a change: the copy is not clean, whatever its files.
        (repo / "imssr" / "agent.py").write_text("LR = 3e-3\n")
        write_stamp(str(repo))
        os.unlink(copy / SOURCE_STAMP)
        shutil.copytree(repo, copy, ignore=shutil.ignore_patterns(".git"), dirs_exist_ok=True)
        assert _state_of(monkeypatch, copy) == (commit, False)
    finally:
        git_state.cache_clear()
    with pytest.raises(ImssrError, match="is not a git checkout"):
        write_stamp(str(copy))


def test_a_record_without_a_commit_says_so():
    rec = {"imssr": "0.2.0", "git_commit": None, "git_clean": None, "torch": "2.13.0", "cuda": None,
           "device_name": "CPU A"}
    assert summary(rec) == "imssr 0.2.0 (commit unknown), torch 2.13.0, CUDA -, on CPU A"
    assert summary({**rec, "git_commit": "b" * 40, "git_clean": False}).startswith("imssr 0.2.0 (bbbbbbb, modified),")


def test_a_damaged_provenance_file_is_kept_aside_and_a_new_one_begun(tmp_path):
    run = RunDir(str(tmp_path / "run"))
    os.makedirs(run.path)
    with open(run.provenance_path, "w") as fh:
        fh.write("{not json")
    assert run.read_provenance() is None
    run.record_provenance({"event": "start"})
    assert run.read_provenance() == [{"event": "start"}]
    assert open(run.provenance_path + ".damaged").read() == "{not json"


def _with_provenance(run_dir, **fields):
    rec = {"event": "start", "agent_step": 0, "imssr": "0.2.0", "git_commit": "a" * 40, "git_clean": True,
           "torch": "2.13.0", "cuda": None, "cudnn": None, "device": "cpu", "device_name": "CPU A", **fields}
    with open(os.path.join(run_dir, "provenance.json"), "w") as fh:
        json.dump({"records": [rec]}, fh)


def test_a_report_names_each_rows_code_and_device_and_warns_when_one_row_mixes_them(tmp_path):
    root, out = str(tmp_path / "sweep"), str(tmp_path / "report")
    _with_provenance(make_run(root, "curl", 1, curve(0, 0, 100)))
    _with_provenance(make_run(root, "curl", 2, curve(0, 0, 200)), device_name="NVIDIA H100 80GB HBM3",
                     cuda="13.0", torch="2.11.0+cu130")
    _with_provenance(make_run(root, "im-curl", 1, curve(0, 0, 300)))
    make_run(root, "im-curl", 2, curve(0, 0, 400))  # imssr before provenance records
    write_report(root, out, reps=20)
    md = open(os.path.join(out, "report.md")).read()
    assert "| `cartpole_swingup_sparse` | curl | imssr 0.2.0 (aaaaaaa), torch 2.11.0+cu130, CUDA 13.0, on " \
           "NVIDIA H100 80GB HBM3 | 1 |" in md
    assert "|  |  | imssr 0.2.0 (aaaaaaa), torch 2.13.0, CUDA -, on CPU A | 1 |" in md
    assert "warning: cartpole_swingup_sparse / curl mixes code versions or devices: " in md
    assert "| im-curl | imssr 0.2.0 (aaaaaaa), torch 2.13.0, CUDA -, on CPU A | 1 |" in md
    assert "|  |  | not recorded (a run of imssr before provenance.json) | 1 |" in md
    assert "im-curl mixes" not in md


def test_an_export_keeps_the_provenance(tmp_path):
    root, dest = str(tmp_path / "sweep"), str(tmp_path / "dest")
    run = str(tmp_path / "sweep" / "cartpole_swingup_sparse" / "curl" / "seed_0")
    train_run(_cfg(), run)
    RunDir(run).write_status("finished", 130)  # as `imssr train` records the end of a run
    exported = export_runs(root, dest)
    assert [e.state for e in exported] == ["new"], exported
    (copied,) = [os.path.join(d, f) for d, _, fs in os.walk(dest) for f in fs if f == "provenance.json"]
    assert open(copied).read() == open(os.path.join(run, "provenance.json")).read()


def test_a_new_run_records_the_data_folders_that_environment_variables_name(tmp_path, monkeypatch):
    """The two environment variables that reach config.json (README): a resume or an evaluation
    in a shell without them reads the same images and footage."""
    from imssr.data import FOOTAGE_DIR_ENV, IMAGE_DIR_ENV
    from imssr.training import Trainer

    images, footage = tmp_path / "images", tmp_path / "clips"
    image_folder(images)
    footage.mkdir()
    monkeypatch.setenv(IMAGE_DIR_ENV, str(images))
    monkeypatch.setenv(FOOTAGE_DIR_ENV, str(footage))
    t = Trainer(tiny_config("soda"), str(tmp_path / "run"))
    t.begin()
    t.close()
    written = json.load(open(tmp_path / "run" / "config.json"))
    assert (written["aux"]["image_dir"], written["env"]["footage_dir"]) == (str(images), str(footage))
