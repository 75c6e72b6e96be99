"""imssr sweep: grid expansion, input errors, and real sweeps on a local Ray (tiny budgets):
resume of an interrupted run, idempotence, retry accounting, and a report of the result."""
import json
import os
import subprocess
import sys

import pytest
import torch

from imssr.cli import main
from imssr.experiments.grid import SweepConfig, build_run_config, expand, load_sweep_file, parse_seeds
from imssr.experiments.runner import DONE_FILE, LOG_FILE
from imssr.training.logger import read_csv

TASK = "cartpole_swingup_sparse"  # 1000 frames per episode, action repeat 8
# The tiny settings of tests/conftest.py as overrides every run of a sweep gets.
TINY = ["train.seed_steps=60", "agent.batch_size=8", "aux.batch_size=8", "agent.hidden_dim=32",
        "agent.feature_dim=16", "agent.encoder_filters=8", "train.replay_capacity=3000",
        "train.eval_every_frames=1000", "train.eval_episodes=1", "train.checkpoint_every_frames=1000",
        "train.tensorboard=false"]


def sweep_cli(*args, check=True):
    proc = subprocess.run([sys.executable, "-m", "imssr", "sweep", "--no-progress", *args],
                          capture_output=True, text=True, timeout=300)
    if check and proc.returncode != 0:
        raise AssertionError(f"imssr sweep failed:\n{proc.stdout}\n{proc.stderr}")
    return proc


def set_args(overrides):
    return [a for o in overrides for a in ("--set", o)]


def status(root):
    with open(os.path.join(root, "sweep_status.json")) as fh:
        return json.load(fh)


def test_seed_lists_and_ranges():
    assert parse_seeds("1,2,3") == [1, 2, 3]
    assert parse_seeds("1-5") == [1, 2, 3, 4, 5]
    assert parse_seeds("0-2, 7, 2") == [0, 1, 2, 7]
    assert parse_seeds([3, "5-6"]) == [3, 5, 6]


def test_grid_directories_and_beta_level(tmp_path):
    cfg = SweepConfig(root=str(tmp_path), algos=["curl", "im-curl"], tasks=["walker_walk", TASK],
                      seeds=[1, 2], beta0=[0.001, 0.05]).validate()
    runs = expand(cfg)
    rel = [os.path.relpath(r.dir, tmp_path) for r in runs]
    # Base algos run once (the beta_0 = 0 reference); each beta_0 has its own level.
    assert rel[:6] == ["walker_walk/curl/seed_1", "walker_walk/curl/seed_2",
                       "walker_walk/im-curl/beta0_0.001/seed_1", "walker_walk/im-curl/beta0_0.001/seed_2",
                       "walker_walk/im-curl/beta0_0.05/seed_1", "walker_walk/im-curl/beta0_0.05/seed_2"]
    assert len(runs) == 12 and len(set(rel)) == 12
    # Each run's config is what `imssr train` builds from the same arguments.
    run = runs[4]
    assert run.train_args(cfg) == ["--algo", "im-curl", "--task", "walker_walk", "--seed", "1", "--beta0", "0.05"]
    built = build_run_config(run, cfg)
    assert (built.intrinsic.beta0, built.train.seed, built.train.frames) == (0.05, 1, 500_000)
    # Without a beta sweep: the preset's beta_0 and no extra level.
    plain = expand(SweepConfig(root=str(tmp_path), algos=["im-curl"], tasks=[TASK], seeds=[3]))
    assert [os.path.relpath(r.dir, tmp_path) for r in plain] == [f"{TASK}/im-curl/seed_3"]
    assert build_run_config(plain[0], cfg).intrinsic.beta0 == 0.01


def test_run_arguments_and_done_marker(tmp_path):
    from imssr.experiments.runner import is_done, last_frame, write_done
    from imssr.experiments.sweep import plan_runs

    cfg = SweepConfig(root=str(tmp_path), algos=["curl"], tasks=[TASK], seeds=[2], frames=3000,
                      gpus_per_run=0.5, overrides=["agent.batch_size=8"])
    (run,) = expand(cfg)
    # A GPU share means training on it, unless the overrides choose a device.
    assert run.train_args(cfg) == ["--algo", "curl", "--task", TASK, "--seed", "2", "--frames", "3000",
                                   "--device", "cuda", "--set", "agent.batch_size=8"]
    cfg.overrides.append("train.device=cuda:1")
    assert "--device" not in run.train_args(cfg)
    os.makedirs(run.dir)
    assert not is_done(run.dir, 3000)
    with open(os.path.join(run.dir, "eval.csv"), "w") as fh:
        fh.write("frame,step,mode,return_mean\n1000,125,training,1.5\n3000,375,training,2.5\n3")  # cut short
    assert last_frame(os.path.join(run.dir, "eval.csv")) == 3000
    write_done(run.dir, 3000, 3000, attempt=1, resumed=False, seconds=12.5)
    assert is_done(run.dir, 3000) and is_done(run.dir, 2000)
    (status,) = plan_runs(cfg)  # a later sweep over the root: skipped, its time still reported
    assert (status.state, status.final_frame, status.seconds) == ("done", 3000, 12.5)
    assert not is_done(run.dir, 4000)  # a larger budget resumes the finished run
    with open(os.path.join(run.dir, DONE_FILE), "w") as fh:
        fh.write('{"frames": 30')  # torn marker: not done
    assert not is_done(run.dir, 3000)


def test_sweep_file_equals_flags(tmp_path, capsys):
    path = tmp_path / "sweep.json"
    path.write_text(json.dumps({"algos": ["curl", "im-curl"], "tasks": TASK, "seeds": "1-2", "frames": 2000,
                                "set": TINY, "retries": 3, "root": str(tmp_path / "r")}))
    from_file = load_sweep_file(str(path)).validate()
    assert (from_file.seeds, from_file.frames, from_file.retries, from_file.overrides) == ([1, 2], 2000, 3, TINY)
    assert main(["sweep", "--file", str(path), "--dry-run"]) == 0
    by_file = capsys.readouterr().out
    assert main(["sweep", "--algos", "curl,im-curl", "--tasks", TASK, "--seeds", "1,2", "--frames", "2000",
                 "--root", str(tmp_path / "r"), *set_args(TINY), "--dry-run"]) == 0
    assert capsys.readouterr().out == by_file
    assert by_file.startswith(f"4 runs under {tmp_path / 'r'}:")
    assert f"{TASK}/im-curl/seed_2\tim-curl {TASK} seed 2, 2000 frames\t[new]" in by_file
    assert not (tmp_path / "r").exists()  # a dry run creates nothing


@pytest.mark.parametrize("args, message", [
    (["--algos", "curl,drq", "--tasks", TASK], "unknown algo 'drq'"),
    (["--algos", "curl", "--tasks", "cartpole_swingup_sparce"], "unknown task 'cartpole_swingup_sparce'"),
    (["--algos", "curl", "--tasks", TASK, "--seeds", "1,x"], "bad seeds 'x'"),
    (["--algos", "curl", "--tasks", TASK, "--seeds", "5-2"], "bad seed range '5-2'"),
    (["--algos", "curl", "--tasks", TASK, "--set", "agent.bogus=1"], "unknown setting 'agent.bogus'"),
    (["--algos", "curl", "--tasks", TASK, "--beta0", "0.1"], "--beta0 needs an algo with an intrinsic reward"),
    (["--algos", "im-curl", "--tasks", TASK, "--beta0", "0.1,-1"], "beta0 values must be >= 0"),
    (["--tasks", TASK], "a sweep needs --algos"),
    (["--file", "/no/such/sweep.json"], "sweep file not found"),
])
def test_bad_input_is_one_line(args, message, tmp_path, capsys):
    assert main(["sweep", "--root", str(tmp_path / "r"), *args, "--dry-run"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("imssr: error: ") and message in err[0], err


def test_unreachable_cluster_fails_at_once_in_one_line(tmp_path, capsys):
    import socket

    with socket.socket() as sock:  # a port that was free a moment ago: nothing listens there
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    assert main(["sweep", "--root", str(tmp_path / "r"), "--algos", "curl", "--tasks", TASK,
                 "--address", f"127.0.0.1:{port}", "--no-progress", *set_args(TINY)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"imssr: error: could not connect to the Ray cluster at 127.0.0.1:{port}: "
                              "nothing answers there"), err


def test_bad_input_has_no_traceback():
    proc = sweep_cli("--algos", "drq", "--tasks", TASK, check=False)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1].startswith("imssr: error: unknown algo 'drq'")


def test_sweep_resumes_interrupted_run_skips_finished_and_reports(tmp_path):
    """Two runs on local Ray: one interrupted beforehand (resumed), one fresh; a re-run starts nothing."""
    from imssr.training import Trainer

    root = str(tmp_path / "sweep")
    grid = ["--root", root, "--algos", "curl,im-curl", "--tasks", TASK, "--seeds", "1", "--frames", "2000",
            *set_args(TINY)]
    cfg = SweepConfig(root=root, algos=["curl", "im-curl"], tasks=[TASK], seeds=[1], frames=2000, overrides=TINY)
    interrupted = expand(cfg)[1]
    # The im-curl run was killed after its first checkpoint (frame 1000 of 2000).  One torch
    # thread, as the sweep gives each run: two spin-waiting threads on a busy 2-core machine
    # are ~15x slower.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    trainer = Trainer(build_run_config(interrupted, cfg), interrupted.dir)
    try:
        trainer.train(stop_at_frame=1000)
    finally:
        trainer.close()
        torch.set_num_threads(threads)
    first_episode = read_csv(os.path.join(interrupted.dir, "train.csv"))[0]

    proc = sweep_cli(*grid)
    assert "2 runs, 0 done, 1 to resume, 1 new" in proc.stdout
    runs = {r["algo"]: r for r in status(root)["runs"]}
    assert status(root)["counts"] == {"queued": 0, "running": 0, "done": 2, "failed": 0}
    assert (runs["im-curl"]["action"], runs["curl"]["action"]) == ("resume", "fresh")
    assert runs["im-curl"]["attempts"] == runs["curl"]["attempts"] == 1
    for run in expand(cfg):
        assert [int(r["frame"]) for r in read_csv(os.path.join(run.dir, "eval.csv"))] == [1000, 2000]
        with open(os.path.join(run.dir, DONE_FILE)) as fh:
            assert json.load(fh)["frames"] == 2000
    # Resumed, not restarted: the episode logged before the interruption is kept as it was.
    assert read_csv(os.path.join(interrupted.dir, "train.csv"))[0] == first_episode
    assert "(resume)" in open(os.path.join(interrupted.dir, LOG_FILE)).read()

    # Idempotence: a finished sweep starts nothing (no Ray, no attempt, no file touched).
    logs = {run.dir: open(os.path.join(run.dir, LOG_FILE)).read() for run in expand(cfg)}
    mtimes = {run.dir: os.path.getmtime(os.path.join(run.dir, "eval.csv")) for run in expand(cfg)}
    proc = sweep_cli(*grid)
    assert "all 2 runs are done; nothing to start" in proc.stdout
    assert {r["state"] for r in status(root)["runs"]} == {"done"}
    assert all(r["attempts"] == 0 for r in status(root)["runs"])
    for run in expand(cfg):
        assert open(os.path.join(run.dir, LOG_FILE)).read() == logs[run.dir]
        assert os.path.getmtime(os.path.join(run.dir, "eval.csv")) == mtimes[run.dir]

    # The report reads the sweep back: one seed each, the final evaluation at T = 2000.
    from imssr.experiments.report import write_report

    write_report(root, str(tmp_path / "report"), reps=50)
    final = {r["label"]: r for r in read_csv(tmp_path / "report" / "table.csv") if r["fraction"] == "1.0"}
    for run in expand(cfg):
        last = read_csv(os.path.join(run.dir, "eval.csv"))[-1]
        assert float(final[run.algo]["mean"]) == pytest.approx(float(last["return_mean"]))
        assert (final[run.algo]["frame"], final[run.algo]["seeds"]) == ("2000", "1")


def test_failing_run_is_retried_then_reported(tmp_path):
    root = str(tmp_path / "sweep")
    # Valid as a config, fails when the run starts: no such device.
    proc = sweep_cli("--root", root, "--algos", "curl", "--tasks", TASK, "--seeds", "4", "--frames", "1000",
                     "--retries", "2", *set_args(TINY + ["train.device=cuda:99"]), check=False)
    assert proc.returncode == 1
    assert "1 of 1 runs failed after retries (curl cartpole_swingup_sparse seed 4)" in proc.stderr
    (run,) = status(root)["runs"]
    assert (run["state"], run["attempts"], len(run["errors"])) == ("failed", 3, 3)
    assert all("cuda:99" in e for e in run["errors"]), run["errors"]
    log = open(os.path.join(root, run["log"])).read()
    assert [line.split(" (")[0] for line in log.splitlines() if line.startswith("==> attempt")] == \
           ["==> attempt 1", "==> attempt 2", "==> attempt 3"]
    assert not os.path.exists(os.path.join(root, os.path.dirname(run["log"]), DONE_FILE))
