"""The sweep directory (imssr.sweep.directory.SweepDir): the names of the files it owns, writes that
are whole or absent, and reads that verify what they read (a damaged file is one line naming it)."""
import errno
import json
import os

import pytest

from imssr.errors import ImssrError
from imssr.sweep.directory import PlannedRun, RunStatus, SweepDir
from imssr.sweep.grid import SweepConfig, expand

TASK = "cartpole_swingup_sparse"


def a_sweep(root):
    """A beta_0 sweep of two runs under ``root``: its settings, its plan, and the runs' states (one
    done, one failed twice)."""
    cfg = SweepConfig(root=str(root), algos=["curl", "im-curl"], tasks=[TASK], seeds=[1], beta0=[0.01])
    done, failed = expand(cfg)
    planned = [PlannedRun(run, 250, 2000, "fp32") for run in (done, failed)]
    statuses = [RunStatus(done, 250, 2000, "done", "done", final_step=250, final_frame=2000, seconds=12.5),
                RunStatus(failed, 250, 2000, "failed", attempts=2,
                          errors=["imssr: error: lost", "imssr: error: diverged at agent step 9: critic loss nan"])]
    return cfg, planned, statuses


def test_the_sweep_files_are_named_under_the_root(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    sweep = SweepDir("sweep")
    assert sweep.path == str(tmp_path / "sweep")  # a relative root is made absolute once
    assert (sweep.plan_path, sweep.status_path, sweep.submitit_dir) == \
        (str(tmp_path / "sweep" / "sweep.json"), str(tmp_path / "sweep" / "sweep_status.json"),
         str(tmp_path / "sweep" / ".submitit"))
    cfg, planned, statuses = a_sweep("sweep")
    assert sweep.write_plan(cfg, planned) == sweep.plan_path
    assert sweep.write_status(statuses, started=0.0, retries=1) == sweep.status_path
    assert sorted(os.listdir(sweep.path)) == ["sweep.json", "sweep_status.json"]


def test_the_plan_and_the_status_read_back_as_written(tmp_path):
    sweep = SweepDir(tmp_path)
    assert (sweep.read_plan(), sweep.read_status(), sweep.failed_runs()) == ([], [], {})  # no sweep yet
    cfg, planned, statuses = a_sweep(tmp_path)
    sweep.write_plan(cfg, planned)
    sweep.write_status(statuses, started=0.0, retries=1, finished=True)
    assert sweep.read_plan() == planned
    assert [p.label for p in sweep.read_plan()] == ["curl", "im-curl beta0=0.01"]
    assert sweep.read_status() == statuses
    # The last error of each run given up on, without the CLI's prefix ...
    assert sweep.failed_runs() == {statuses[1].run.dir: "diverged at agent step 9: critic loss nan"}
    # ... unless it finished since.
    os.makedirs(statuses[1].run.dir)
    statuses[1].run.run_dir.write_done(250, 250, attempt=3, resumed=True)
    assert sweep.failed_runs() == {}


def test_a_running_row_of_a_sweep_that_is_gone_reads_as_interrupted(tmp_path):
    """A sweep killed outright leaves its running rows behind: a run whose training stopped too
    is interrupted, one whose training goes on (a SLURM job) is still running."""
    sweep = SweepDir(tmp_path)
    _, _, statuses = a_sweep(tmp_path)
    for st in statuses:
        st.state, st.errors = "running", []
    with sweep.lock():  # as the sweep holds its root while it runs
        sweep.write_status(statuses, started=0.0, retries=1)
        assert [st.state for st in sweep.read_status()] == ["running", "running"]
    training = statuses[0].run.run_dir.open()  # as its training holds the run
    try:
        read = sweep.read_status()
    finally:
        training.release()
    assert [st.state for st in read] == ["running", "interrupted"]
    assert "the next sweep resumes it" in read[1].note


def test_a_status_row_that_cannot_be_read_hides_only_itself_from_the_failures(tmp_path):
    sweep = SweepDir(tmp_path)
    cfg, planned, statuses = a_sweep(tmp_path)
    sweep.write_status(statuses, started=0.0, retries=1)
    data = json.loads(open(sweep.status_path).read())
    data["runs"][0]["seed"] = "one"  # a hand edit: the done run's row no longer reads
    with open(sweep.status_path, "w") as fh:
        json.dump(data, fh)
    with pytest.raises(ImssrError, match="is damaged"):
        sweep.read_status()
    assert sweep.failed_runs() == {statuses[1].run.dir: "diverged at agent step 9: critic loss nan"}


@pytest.mark.parametrize("which", ["plan", "status"])
def test_a_write_that_fails_leaves_the_file_as_it_was(which, tmp_path, monkeypatch):
    """A full disk while the new file is written: a one-line error, the old file whole, and no
    temporary file left beside it."""
    import imssr.files

    sweep = SweepDir(tmp_path)
    cfg, planned, statuses = a_sweep(tmp_path)
    write = {"plan": lambda: sweep.write_plan(cfg, planned),
             "status": lambda: sweep.write_status(statuses, started=0.0, retries=1)}[which]
    path = write()
    before = open(path, "rb").read()
    planned.pop()
    statuses.pop()

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(imssr.files.os, "fsync", full)
    with pytest.raises(ImssrError, match=f"^no space left on .* while writing {path}"):
        write()
    assert open(path, "rb").read() == before
    assert sorted(os.listdir(tmp_path)) == [os.path.basename(path)]


@pytest.mark.parametrize("which", ["plan", "status"])
@pytest.mark.parametrize("content, problem", [
    (b'{"runs": [{"algo": "curl"', "is not valid JSON"),  # cut short
    (b"\xff\xfe{}", "is not a JSON text file (it is not UTF-8 text)"),
    (b"[" * 100_000, "nests its JSON too deeply"),
    (b'["runs"]', "is damaged: the file is not an object but list"),
    (b'{"runs": [{"algo": "curl", "task": "t", "seed": 1, "dir": "x"}]}', "is damaged: run 1 has no"),
    (b'{"runs": [{"algo": "curl", "task": "t", "seed": "1", "dir": "x", "steps": 1, "state": "done"}]}',
     "is damaged: run 1 has 'seed' '1'"),
])
def test_a_damaged_file_is_one_line_naming_it(which, content, problem, tmp_path):
    sweep = SweepDir(tmp_path)
    path = {"plan": sweep.plan_path, "status": sweep.status_path}[which]
    with open(path, "wb") as fh:
        fh.write(content)
    with pytest.raises(ImssrError) as error:
        sweep.read_plan() if which == "plan" else sweep.read_status()
    message = str(error.value)
    assert len(message.splitlines()) == 1 and path in message and problem in message, message
    assert sweep.failed_runs() == {}  # what the report reads of a damaged status: no failure
