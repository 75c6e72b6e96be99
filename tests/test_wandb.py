"""Weights & Biases logging with the real library in offline mode (no server): what it writes,
the same W&B run continued across a kill -9 and --resume, and a W&B that cannot write."""
import glob
import json
import os
import subprocess
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
