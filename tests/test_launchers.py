"""imssr sweep --launcher local|slurm: the same plan, retries, status file and resume as the Ray
path, with real `imssr train` processes on tiny budgets (SLURM through submitit's local executor)."""
import os
import subprocess
import sys
import time

import pytest

from conftest import SWEEP_TINY as TINY
from conftest import cli_config, kill_when_file_appears, sweep_status
from imssr.cli import main
from imssr.sweep.directory import SweepDir
from imssr.sweep.grid import SweepConfig, expand
from imssr.rundir import DONE_FILE, SWEEP_LOG
from imssr.sweep.sweep import run_sweep

TASK = "cartpole_swingup_sparse"  # 125 agent steps per episode at action repeat 8


def attempts_in_log(run_dir):
    with open(os.path.join(run_dir, SWEEP_LOG)) as fh:
        return [line for line in fh if line.startswith("==> attempt")]


def test_killed_local_driver_rerun_skips_finished_runs(tmp_path):
    """`--launcher local`, one run at a time: the driver is killed (-9) once the first run is
    done; the same command then skips it and finishes the second."""
    root = str(tmp_path / "sweep")
    cmd = [sys.executable, "-m", "imssr", "sweep", "--no-progress", "--launcher", "local", "--max-parallel", "1",
           "--root", root, "--algos", "curl", "--tasks", TASK, "--seeds", "1,2", "--steps", "125",
           *[a for o in TINY for a in ("--set", o)]]
    first, second = expand(SweepConfig(root=root, algos=["curl"], tasks=[TASK], seeds=[1, 2]))
    driver = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    kill_when_file_appears(driver, os.path.join(first.dir, DONE_FILE), 240, "the first run did not finish")
    # The training the driver had started dies with it (its run directory's lock is free).
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "2 runs, 1 done" in proc.stdout and "(local)" in proc.stdout
    runs = {r["seed"]: r for r in sweep_status(root)["runs"]}
    assert (runs[1]["action"], runs[1]["attempts"], runs[1]["state"]) == ("done", 0, "done")
    assert (runs[2]["attempts"], runs[2]["state"], runs[2]["final_step"]) == (1, "done", 125)
    assert len(attempts_in_log(first.dir)) == 1  # never started again
    assert os.path.exists(os.path.join(second.dir, DONE_FILE))


def test_slurm_launcher_through_submitit_local_executor(tmp_path):
    """`--launcher slurm`'s code path with submitit's local executor: one job per run attempt,
    a failing run retried, the status file written; a second sweep starts nothing."""
    root = str(tmp_path / "sweep")
    cfg = SweepConfig(root=root, algos=["curl"], tasks=[TASK], seeds=[1], steps=125, overrides=TINY,
                      launcher="slurm", slurm_time=10, retries=1).validate()
    statuses = run_sweep(cfg, progress=False, poll_s=0.5, submitit_cluster="local")
    assert [(s.state, s.attempts, s.final_step) for s in statuses] == [("done", 1, 125)]
    (run,) = expand(cfg)
    assert os.path.exists(os.path.join(run.dir, DONE_FILE))
    assert sweep_status(root)["counts"] == {"queued": 0, "running": 0, "done": 1, "failed": 0, "interrupted": 0}
    assert os.listdir(SweepDir(root).submitit_dir)  # submitit's job folders
    again = run_sweep(cfg, progress=False, poll_s=0.5, submitit_cluster="local")
    assert [(s.state, s.action, s.attempts) for s in again] == [("done", "done", 0)]
    # A run that fails (no such device) is retried as a new job, then reported.
    bad = SweepConfig(root=str(tmp_path / "bad"), algos=["curl"], tasks=[TASK], seeds=[2], steps=125,
                      overrides=TINY + ["train.device=cuda:99"], launcher="slurm", retries=1).validate()
    (st,) = run_sweep(bad, progress=False, poll_s=0.5, submitit_cluster="local")
    assert (st.state, st.attempts, len(st.errors)) == ("failed", 2, 2)
    assert all("cuda:99" in e for e in st.errors), st.errors


@pytest.mark.parametrize("args, message", [
    (["--launcher", "ray", "--slurm-time", "60"], "the --slurm-* settings go with --launcher slurm"),
    (["--launcher", "local", "--address", "10.0.0.1:6379"], "--address (a Ray cluster) goes with --launcher ray"),
    (["--logger", "csv,mlflow"], "unknown logger 'mlflow' in --logger"),
])
def test_bad_launcher_settings_are_one_line(args, message, tmp_path, capsys):
    assert main(["sweep", "--root", str(tmp_path / "r"), "--algos", "curl", "--tasks", TASK, *args,
                 "--dry-run"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("imssr: error: ") and message in err[0], err


def test_slurm_without_sbatch_is_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))  # no sbatch on it
    assert main(["sweep", "--root", str(tmp_path / "r"), "--algos", "curl", "--tasks", TASK,
                 "--launcher", "slurm", "--slurm-partition", "gpu"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--launcher slurm needs SLURM's sbatch" in err[0], err
    assert not (tmp_path / "r").exists()  # nothing written


def test_sweep_logger_groups_and_tags_wandb_runs(tmp_path):
    from imssr.rundir import RunDir
    from imssr.training.wandb_run import run_tags

    cfg = SweepConfig(root=str(tmp_path / "table1"), algos=["im-curl"], tasks=[TASK], seeds=[3], beta0=[0.05],
                      logger="csv,wandb").validate()
    (run,) = expand(cfg)
    built = run.resolved_config(cfg)
    assert built == cli_config("--config", RunDir(run.dir).write_config(built), "--out", run.dir)
    assert (built.train.wandb, built.train.tensorboard, built.train.wandb_group) == (True, False, "table1")
    assert run_tags(built) == ["im-curl", TASK, "seed_3", "beta0_0.05"]


def test_killed_slurm_driver_rerun_skips_finished_runs(tmp_path):
    """The SLURM launcher (submitit's local executor): the driver is killed (-9) once the first run
    is done; jobs it submitted may outlive it, as SLURM jobs do.  Once nothing trains in the run
    directories any more, the same sweep starts nothing for finished runs and completes the rest."""
    from imssr.rundir.lock import DirectoryLock

    root = str(tmp_path / "sweep")
    script = (f"from imssr.sweep.grid import SweepConfig\nfrom imssr.sweep.sweep import run_sweep\n"
              f"cfg = SweepConfig(root={root!r}, algos=['curl'], tasks=[{TASK!r}], seeds=[1, 2], steps=125, "
              f"overrides={TINY!r}, launcher='slurm', retries=1).validate()\n"
              f"print([s.state for s in run_sweep(cfg, progress=False, poll_s=0.5, submitit_cluster='local')])\n")
    first, second = expand(SweepConfig(root=root, algos=["curl"], tasks=[TASK], seeds=[1, 2]))
    driver = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    kill_when_file_appears(driver, os.path.join(first.dir, DONE_FILE), 300, "the first run did not finish")
    deadline = time.time() + 300
    while True:  # an orphaned job may still be training the second run
        try:
            DirectoryLock(second.dir).acquire().release()
            break
        except Exception:  # noqa: BLE001 - in use
            assert time.time() < deadline, "the second run's training never ended"
            time.sleep(1.0)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "['done', 'done']"
    runs = {r["seed"]: r for r in sweep_status(root)["runs"]}
    assert (runs[1]["action"], runs[1]["attempts"], runs[1]["state"]) == ("done", 0, "done")
    assert runs[2]["state"] == "done" and runs[2]["final_step"] == 125
    assert len(attempts_in_log(first.dir)) == 1  # never started again


def test_a_run_whose_sweep_log_cannot_be_written_fails_in_one_line_and_the_sweep_goes_on(tmp_path, tiny_fs):
    """Each run's directory is a file system with room for its config.json and no file more: the
    attempt starts no training (its log cannot be created), the sweep says so in one line per
    run, marks both failed and ends."""
    root = str(tmp_path / "sweep")
    cfg = SweepConfig(root=root, algos=["curl"], tasks=[TASK], seeds=[1, 2])
    runs = expand(cfg)
    for run in runs:
        tiny_fs("1m", at=run.dir, inodes=2)  # the folder itself and config.json
    cmd = [sys.executable, "-m", "imssr", "sweep", "--no-progress", "--launcher", "local", "--retries", "0",
           "--root", root, "--algos", "curl", "--tasks", TASK, "--seeds", "1,2", "--steps", "10",
           *[a for o in TINY for a in ("--set", o)]]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1, proc.stdout + proc.stderr  # runs failed
    assert "Traceback" not in proc.stderr
    failed = [line for line in proc.stdout.splitlines() if line.startswith("FAILED")]
    assert len(failed) == 2, proc.stdout
    for run, line in zip(runs, sorted(failed)):
        assert f"no space left on {run.dir} while writing {run.dir}/{SWEEP_LOG}" in line, line
    assert [r["state"] for r in sweep_status(root)["runs"]] == ["failed", "failed"]


def test_every_launcher_fails_an_attempt_whose_sweep_log_cannot_be_written(tmp_path):
    """A folder where the log goes: no process starts, the attempt fails in one line (the body of
    a Ray task and a SLURM job alike), and the local launcher's wait sees it ended."""
    from imssr.sweep.launchers import LocalLauncher
    from imssr.sweep.runner import RunAttempt, execute_runs

    run_dir = str(tmp_path / "run")
    os.makedirs(os.path.join(run_dir, SWEEP_LOG))
    result = execute_runs([run_dir], 10, 1)[0]
    assert not result["ok"] and result["returncode"] is None
    assert result["error"] == f"cannot write {run_dir}/{SWEEP_LOG}: Is a directory"
    attempt = RunAttempt(run_dir, 10, 1)
    assert LocalLauncher(SweepConfig(launcher="local")).wait([attempt], timeout_s=0.5) == [attempt]
