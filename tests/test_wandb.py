"""Weights & Biases logging with the real library in offline mode (no server): what it writes,
the same W&B run continued across a kill -9 and --resume, and a W&B that cannot write."""
import glob
import json
import os
import subprocess
import time
import sys

import pytest

from conftest import cli_config, kill_when_file_appears, tiny_sets
from imssr.cli import main
from imssr.rundir import WANDB_RUN_FILE as RUN_ID_FILE, RunDir
from imssr.training.wandb_run import read_run_id

pytest.importorskip("wandb")

TASK = "cartpole_swingup_sparse"
TINY_ARGS = ["--algo", "im-curl", "--task", TASK, "--steps", "250", "--seed-steps", "60", "--eval-every", "125",
             "--eval-episodes", "1", "--checkpoint-every", "125", "--no-progress",
             "--set", "train.burst_updates=0", *tiny_sets(), "--set", "train.replay_capacity=3000"]


def offline_runs(wandb_dir):
    return sorted(glob.glob(os.path.join(wandb_dir, "wandb", "offline-run-*")))


def test_offline_run_across_kill_and_resume(tmp_path):
    """A real training killed (-9) after its first checkpoint, then resumed: both processes log
    to the same W&B run id, with the config, the scalars, the videos and the learning curve."""
    run_dir, wandb_dir = str(tmp_path / "run"), str(tmp_path / "wb")
    env = dict(os.environ, WANDB_MODE="offline", WANDB_DIR=wandb_dir, OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "imssr", "train", *TINY_ARGS, "--logger", "csv,wandb",
           "--set", "train.eval_video_every=1", "--out", run_dir]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    kill_when_file_appears(proc, os.path.join(run_dir, "checkpoints", "latest.pt"), 240,
                           "no checkpoint before the kill", poll=0.2)
    run_id = read_run_id(RunDir(run_dir))
    assert run_id and len(offline_runs(wandb_dir)) == 1
    resumed = subprocess.run([sys.executable, "-m", "imssr", "train", "--resume", "--out", run_dir,
                              "--no-progress"], env=env, capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    assert "resuming from agent step 125" in resumed.stdout
    # The same W&B run: the id kept in the run directory, one offline directory per process.
    assert read_run_id(RunDir(run_dir)) == run_id
    runs = offline_runs(wandb_dir)
    assert len(runs) == 2 and all(r.endswith(f"-{run_id}") for r in runs)
    for r in runs:
        assert os.path.getsize(os.path.join(r, f"run-{run_id}.wandb")) > 0
    # What the resumed process wrote: the scalars TensorBoard gets, the config, the tags, the
    # evaluation video (the step-250 evaluation) and the learning curve.
    records = open(os.path.join(runs[-1], f"run-{run_id}.wandb"), "rb").read()
    for text in (b"train/critic_loss", b"eval/training/return_mean", b"update_schedule", b"im-curl",
                 b"seed_0", b"beta0_"):
        assert text in records, text
    media = [os.path.basename(p) for p in glob.glob(os.path.join(runs[-1], "files", "media", "**", "*.*"),
                                                   recursive=True)]
    assert any(m.startswith("training_video") and m.endswith(".gif") for m in media), media
    assert any(m.startswith("learning_curve") and m.endswith(".png") for m in media), media
    assert os.path.exists(os.path.join(run_dir, "videos", "step_000000250_training.gif"))


def test_unwritable_wandb_dir_warns_once_and_training_goes_on(tmp_path, capsys, monkeypatch):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_DIR", str(blocker / "wandb"))  # under a file: nobody can create it
    out = tmp_path / "run"
    assert main(["train", *TINY_ARGS, "--steps", "125", "--logger", "csv,wandb", "--out", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    warnings = [line for line in lines if "Weights & Biases is off" in line]
    assert len(warnings) == 1 and "is not writable" in warnings[0], lines
    assert os.path.exists(out / "eval.csv") and os.path.exists(out / RUN_ID_FILE)


@pytest.mark.parametrize("args, message", [
    (["--logger", "csv,wandb,mlflow"], "unknown logger 'mlflow' in --logger; choose from csv, tensorboard, wandb"),
    (["--logger", "csv,tensorboard", "--no-tensorboard"], "--no-tensorboard and --logger ...tensorboard contradict"),
])
def test_bad_logger_is_one_line(args, message, tmp_path, capsys):
    assert main(["train", *TINY_ARGS, *args, "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("imssr: error: ") and message in err[0], err


def test_missing_extra_is_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "wandb", None)  # what `import wandb` finds without the extra
    assert main(["train", *TINY_ARGS, "--logger", "csv,wandb", "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [err[0]] and err[0].startswith("imssr: error: wandb is not installed (needed by imssr wandb): "
                                                 "pip install 'imssr[wandb]'"), err


def test_logger_flag_sets_the_config_and_keeps_no_tensorboard(tmp_path):
    def cfg(*args):
        return cli_config(*TINY_ARGS, *args).train

    assert (cfg().tensorboard, cfg().wandb) == (True, False)
    assert (cfg("--no-tensorboard").tensorboard, cfg("--no-tensorboard").wandb) == (False, False)
    assert (cfg("--logger", "csv,wandb").tensorboard, cfg("--logger", "csv,wandb").wandb) == (False, True)
    assert cfg("--logger", "tensorboard,wandb", "--set", "train.wandb_project=p").wandb_project == "p"
    with open(tmp_path / "c.json", "w") as fh:
        json.dump({"algo": "im-curl", "env": {"task": TASK}, "train": {"wandb": True}}, fh)
    assert cfg("--config", str(tmp_path / "c.json")).wandb is True


def _csv_series(run_dir):
    """``(series, frame)`` of every row of train.csv and eval.csv."""
    from imssr.files import read_csv

    rows = {("train", int(float(r["frame"]))) for r in read_csv(os.path.join(run_dir, "train.csv"))}
    return rows | {(f"eval/{r['mode']}", int(float(r["frame"]))) for r in read_csv(os.path.join(run_dir, "eval.csv"))}


def test_history_across_kill_and_fall_back_holds_every_csv_row_once(tmp_path):
    """Killed (-9) at its first checkpoint and resumed to its end, then resumed again from that
    checkpoint (latest.pt unreadable, the later ones gone): the W&B run's records, read back from
    the three processes' offline files, hold every row of the CSVs once, in frame order, with the
    CSVs' values."""
    from imssr.files import read_csv
    from imssr.training.wandb_records import history_rows, run_files, series_of

    run_dir, wandb_dir = str(tmp_path / "run"), str(tmp_path / "wb")
    env = dict(os.environ, WANDB_MODE="offline", WANDB_DIR=wandb_dir, OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "imssr", "train", *TINY_ARGS, "--logger", "csv,wandb",
           "--set", "train.keep_checkpoints=3", "--out", run_dir]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    checkpoints = os.path.join(run_dir, "checkpoints")
    kill_when_file_appears(proc, os.path.join(checkpoints, "step-000000125.pt"), 240,
                           "no checkpoint before the kill", poll=0.05)
    resume = [sys.executable, "-m", "imssr", "train", "--resume", "--out", run_dir, "--no-progress"]
    resumed = subprocess.run(resume, env=env, capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    with open(os.path.join(checkpoints, "latest.pt"), "wb") as fh:
        fh.write(b"torn")
    for later in glob.glob(os.path.join(checkpoints, "step-*.pt")):
        if not later.endswith("step-000000125.pt"):
            os.unlink(later)
    again = subprocess.run(resume, env=env, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stdout + again.stderr
    assert "resuming from step-000000125.pt at agent step 125" in again.stdout, again.stdout
    run_id = read_run_id(RunDir(run_dir))
    assert len(run_files(wandb_dir, run_id)) == 3
    rows = [row for path in run_files(wandb_dir, run_id) for row in history_rows(path)]
    rows = [row for row in rows if any(k.startswith(("train/", "eval/")) for k in row)]
    logged = [(series_of(next(k for k in row if "/" in k)), int(row["frame"])) for row in rows]
    assert sorted(logged) == sorted(set(logged)), "a row logged twice"
    assert set(logged) == _csv_series(run_dir)
    assert [f for _, f in logged] == sorted(f for _, f in logged), "not in frame order"
    returns = {int(float(r["frame"])): float(r["episode_return"]) for r in read_csv(os.path.join(run_dir, "train.csv"))}
    for row in rows:
        if "train/episode_return" in row:
            assert row["train/episode_return"] == pytest.approx(returns[int(row["frame"])], rel=1e-5)


def test_records_are_read_back_and_a_torn_file_gives_what_precedes_the_tear(tmp_path, monkeypatch):
    """The history rows of a real offline W&B run, read back from its .wandb file in the order
    logged; the file cut anywhere (a kill -9 mid-write) gives a prefix of them."""
    import wandb

    from imssr.training.wandb_records import history_rows, logged_series, run_files

    monkeypatch.setenv("WANDB_MODE", "offline")
    run = wandb.init(project="p", id="abc123", dir=str(tmp_path), reinit="create_new",
                     settings=wandb.Settings(console="off", quiet=True, save_code=False))
    for i in range(300):  # more than one 32 KiB block
        run.log({"train/x": i * 1.5, "train/pad": "y" * 200, "frame": 8 * i, "step": i})
    run.log({"eval/training/return_mean": 3.0, "frame": 8 * 299, "step": 299})
    run.finish()
    (path,) = run_files(str(tmp_path), "abc123")
    deadline = time.time() + 30
    while len(history_rows(path)) < 301 and time.time() < deadline:  # W&B's service writes on after finish
        time.sleep(0.1)
    rows = history_rows(path)
    assert [(r["train/x"], r["frame"]) for r in rows[:300]] == [(i * 1.5, 8 * i) for i in range(300)]
    assert logged_series(str(tmp_path), "abc123") == {("train", 8 * i) for i in range(300)} | {("eval/training", 2392)}
    data = open(path, "rb").read()
    for cut in (len(data) // 3, len(data) // 2 + 5, len(data) - 3):  # the last: in the run's exit record
        with open(path, "wb") as fh:
            fh.write(data[:cut])
        torn = history_rows(path)
        assert torn == rows[:len(torn)] and (len(torn) < len(rows)) == (cut < len(data) - 3)
