"""The command line: tiny end-to-end runs per algorithm, evaluate, kill + resume, errors."""
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from conftest import cli_help, cli_status, image_folder, run_imssr, tiny_sets
from imssr.training.logger import read_csv

TINY = ["--steps", "250", "--seed-steps", "60", "--eval-every", "125", "--eval-episodes", "1",
        "--replay-capacity", "3000", "--no-progress", *tiny_sets(), "--set", "train.burst_updates=0"]


imssr = run_imssr


# Every algorithm trains in-process in test_algorithms.py; the CLI trains one, with the most
# moving parts: an intrinsic reward, an auxiliary task, overlay images from a user folder.
def test_train_end_to_end_then_evaluate_in_scenes(tmp_path):
    out = tmp_path / "im-soda"
    image_folder(tmp_path / "images")
    imssr("train", "--algo", "im-soda", "--task", "cartpole_swingup_sparse", "--seed", "1", "--out", str(out),
          *TINY, "--image-dir", str(tmp_path / "images"))
    for name in ("config.json", "train.csv", "eval.csv", "learning_curve.png", "checkpoints/latest.pt"):
        assert (out / name).exists(), name
    rows = read_csv(out / "eval.csv")
    assert [(r["frame"], r["step"], r["mode"]) for r in rows] == [("1000", "125", "training"),
                                                                    ("2000", "250", "training")]
    assert {"frame", "step", "mode", "return_mean", "return_std", "episodes"} <= set(rows[0])
    train = read_csv(out / "train.csv")
    assert len(train) == 2 and float(train[1]["critic_loss"]) > 0
    assert float(train[1]["beta"]) > 0 and float(train[1]["r_int_std"]) > 0
    # Test scenes, one gif per scene and a montage.
    modes = ["training", "color_hard", "video_hard"]
    proc = imssr("evaluate", "--run", str(out), "--episodes", "1", "--modes", ",".join(modes),
                 "--video", "gif", "--montage")
    assert all(f"{m}: return" in proc.stdout for m in modes)
    assert f"imssr: evaluation written to {out / 'evaluate.csv'} and {out / 'evaluate_episodes.csv'}" \
        in proc.stdout
    assert [r["mode"] for r in read_csv(out / "evaluate.csv")] == modes
    assert [r["mode"] for r in read_csv(out / "evaluate_episodes.csv")] == modes
    for m in modes:
        assert (out / "videos" / f"{m}.gif").stat().st_size > 1000
    assert (out / "montage.png").stat().st_size > 1000


def test_killed_run_resumes_to_completion(tmp_path):
    out = tmp_path / "killed"
    args = ["train", "--algo", "im-curl", "--task", "cartpole_swingup_sparse", "--out", str(out),
            *TINY, "--steps", "375", "--checkpoint-every", "125"]
    proc = subprocess.Popen([sys.executable, "-m", "imssr", *args],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    latest = out / "checkpoints" / "latest.pt"
    deadline = time.time() + 600  # generous: a busy machine can be slow; exits as soon as it exists
    while not latest.exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert latest.exists()
    imssr("train", "--out", str(out), "--resume", "--no-progress")
    rows = read_csv(out / "eval.csv")
    frames = [int(r["frame"]) for r in rows]
    assert frames == sorted(set(frames)) and frames[-1] == 3000
    assert [int(r["frame"]) for r in read_csv(out / "train.csv")] == [1000, 2000, 3000]


@pytest.mark.parametrize("args, message", [
    (["train", "--algo", "im-curl", "--task", "cartpole_swingup_sparce"], "unknown task 'cartpole_swingup_sparce'"),
    (["train", "--algo", "drq", "--task", "walker_walk"], "invalid choice: 'drq'"),
    (["train", "--algo", "curl", "--task", "walker_walk", "--frames", "-5"], "expected a positive integer"),
    (["train", "--algo", "curl", "--task", "walker_walk", "--beta0", "0.1"], "--beta0 applies to algorithms with an intrinsic"),
    (["train", "--algo", "soda", "--task", "walker_walk", "--image-dir", "/no/such/dir"], "image folder not found"),
    (["train", "--algo", "curl"], "needs --algo and --task"),
    (["train", "--algo", "curl", "--task", "walker_walk", "--set", "agent.bogus=1"], "unknown setting"),
    (["train", "--algo", "curl", "--task", "walker_walk", "--device", "cuda:0"], "CUDA is not available"),
    (["train", "--algo", "curl", "--task", "walker_walk", "--config", "/no/such.json"], "config file not found"),
    (["train", "--out", "/no/such/run", "--resume"], "nothing to resume"),
    (["evaluate", "--run", "/no/such/run"], "run directory not found"),
    (["train", "--algo", "curl", "--task", "walker_walk", "--mode", "video_medium"], "unknown mode 'video_medium'"),
    (["train", "--algo", "curl", "--task", "walker_walk", "--eval-modes", "training,colour_hard"],
     "unknown mode 'colour_hard'"),
    (["train", "--algo", "curl", "--task", "walker_walk", "--footage", "/no/such/videos"], "footage not found"),
])
def test_errors_are_one_line(args, message, tmp_path, capsys):
    """In this process (:func:`cli_status`); test_an_error_of_the_command_itself_is_one_line runs
    one in a process of its own."""
    if "--device" in args:
        import torch

        if torch.cuda.is_available():
            pytest.skip("CUDA present")
    if args[0] == "train" and "--out" not in args:
        args = [*args, "--out", str(tmp_path / "x")]
    assert cli_status(*args) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert message in lines[-1], err
    assert not (tmp_path / "x").exists()


def test_an_error_of_the_command_itself_is_one_line(tmp_path):
    proc = imssr("train", "--algo", "im-curl", "--task", "cartpole_swingup_sparce", "--out", str(tmp_path / "x"),
                 check=False)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("imssr: error: unknown task 'cartpole_swingup_sparce'"), lines
    assert not (tmp_path / "x").exists()


def test_tasks_and_algos_listings():
    tasks = imssr("tasks").stdout
    for name in ("cartpole_swingup_sparse", "walker_walk_sparse", "finger_spin", "ball_in_cup_catch"):
        assert name in tasks
    algos = imssr("algos").stdout
    names = {line.split("\t")[0] for line in algos.splitlines()}
    assert names == {f"{p}{b}{s}" for b in ("curl", "soda", "pad", "svea")
                     for p, s in (("", ""), ("im-", ""), ("", "+rnd"), ("", "+re3"))}
    assert '"beta0": 0.05' in imssr("config", "--algo", "im-curl", "--task", "pendulum_swingup").stdout


@pytest.mark.parametrize("args, message", [
    (["--seed", "18446744073709551616"], "train.seed must be an integer in [0, 2147483647] (numpy and dm_control "
                                         "take 32-bit seeds, and evaluation adds up to 20000), got 18446744073709551616"),
    (["--set", "train.seed=1e30"], "train.seed must be an integer in [0, 2147483647]"),
    (["--set", "agent.batch_size=NaN"], "agent.batch_size expects an integer, got 'NaN'"),
    (["--set", "agent.batch_size=Infinity"], "agent.batch_size expects an integer, got 'Infinity'"),
    (["--set", "agent.batch_size=1e400"], "agent.batch_size expects an integer, got '1e400'"),
    (["--set", "agent.actor_lr=NaN"], "agent.actor_lr expects a finite number, got 'NaN'"),
    (["--set", "agent.init_temperature=Infinity"], "agent.init_temperature expects a finite number, got 'Infinity'"),
    (["--beta0", "inf"], "intrinsic.beta0 must be a finite number, got inf"),
    (["--out", ""], "--out is empty"),
])
def test_bad_values_are_one_line_errors_before_anything_starts(args, message, tmp_path, capsys):
    argv = ["train", "--algo", "im-curl", "--task", "walker_walk", *args]
    if "--out" not in args:
        argv += ["--out", str(tmp_path / "run")]
    assert cli_status(*argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("imssr: error: ") and message in err[0], err
    assert not (tmp_path / "run").exists() and not os.path.exists("runs/walker_walk/im-curl")


def test_binary_config_file_is_a_one_line_error(tmp_path, capsys):
    binary = tmp_path / "latest.pt"
    binary.write_bytes(bytes(range(256)) * 8)
    assert cli_status("train", "--config", str(binary), "--out", str(tmp_path / "run")) == 2
    assert capsys.readouterr().err.strip().splitlines() == \
        [f"imssr: error: config file {binary} is not a JSON text file (it is not UTF-8 text)"]


def test_every_option_of_every_subcommand_says_its_default():
    # Read from what `--help` prints: "  --flag METAVAR   help text", the help on the next lines when
    # the option's own text is long.
    commands = re.findall(r"^    ([a-z]+) ", cli_help(), flags=re.M)
    assert set(commands) >= {"train", "demo", "evaluate", "analyze", "modes", "plot", "sweep", "report", "export",
                             "tasks", "algos", "config"}
    missing = []
    for name in commands:
        text = cli_help(name)
        usage = text.split("\n\n")[0]
        entries = re.findall(r"^  (?:-\w, )?(--[\w-]+)( \S+)?(.*(?:\n {5,}\S.*)*)", text, flags=re.M)
        for flag, metavar, help_text in entries:
            if not metavar:
                continue  # a flag (--resume, -h): no value, no default
            if f"[{flag}" not in usage:
                continue  # a required option has no default
            if "default" not in help_text:
                missing.append(f"{name} {flag}: {help_text!r}")
    assert not missing, missing
    assert "(default: 10)" in cli_help("evaluate")


def test_a_closed_stdout_drops_the_progress_not_the_training(tmp_path):
    """`imssr train ... | head -1`: the reader is gone before the first line; the run trains to
    its budget and checkpoints, and nothing about the pipe reaches stderr."""
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "imssr", "train", "--algo", "curl", "--task",
                             "cartpole_swingup_sparse", "--out", str(out), *TINY, "--steps", "10", "--seed-steps", "5"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    proc.stdout.close()
    err = proc.stderr.read()
    assert proc.wait(timeout=600) == 0, err
    assert "Broken pipe" not in err and "Traceback" not in err and "Exception ignored" not in err, err
    assert (out / "checkpoints" / "latest.pt").exists()
    assert '"state": "finished"' in (out / "status.json").read_text()


def test_a_seed_phase_as_long_as_the_budget_warns_that_the_agent_never_learns(tmp_path, capsys):
    from conftest import tiny_config
    from imssr.training import Trainer

    for seed_steps, warned in ((10, True), (9, False)):
        t = Trainer(tiny_config("curl", steps=10, seed_steps=seed_steps), str(tmp_path / f"run{seed_steps}"))
        t.begin()
        t.close()
        lines = [line for line in capsys.readouterr().out.splitlines() if "never updated" in line]
        assert lines == (["imssr: warning: the seed phase (--seed-steps) acts at random until agent step 10 "
                          "and the budget (--steps) ends at 10: the agent is never updated"] if warned else [])


@pytest.mark.parametrize("args, message", [
    (["train", "--seed", "-1"], "argument --seed: expected an integer >= 0, got '-1'"),
    (["train", "--steps", "0"], "argument --steps: expected a positive integer, got '0'"),
    (["evaluate"], "the following arguments are required: --run"),
])
def test_bad_arguments_are_one_line_not_the_usage(args, message, capsys):
    from imssr.cli import main

    with pytest.raises(SystemExit) as exit_:
        main(args)
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"imssr: error: {message} (see imssr {args[0]} --help)"]
