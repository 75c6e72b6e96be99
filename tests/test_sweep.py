"""imssr sweep: grid expansion, input errors, and real sweeps on a local Ray (tiny budgets):
resume of an interrupted run, idempotence, retry accounting, and a report of the result."""
import json
import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import fields, replace

import pytest
import torch

from conftest import SWEEP_TINY as TINY
from conftest import a_checkpoint, cli_config, cli_help, sweep_status, tiny_config, train_stopped_at
from imssr.cli import _sweep_config, build_parser, main
from imssr.config import dataclass_field_docs
from imssr.contention import autogroup, autogroup_scheduling
from imssr.rundir import DONE_FILE, SWEEP_LOG, RunDir
from imssr.sweep.directory import SweepDir
from imssr.sweep.grid import SweepConfig, expand, load_sweep_file, parse_seeds, setting_key
from imssr.sweep.runner import execute_runs
from imssr.sweep.sweep import plan_runs, settle
from imssr.training.logger import read_csv

TASK = "cartpole_swingup_sparse"  # 1000 frames = 125 agent steps per episode, action repeat 8


def sweep_cli(*args, check=True):
    proc = subprocess.run([sys.executable, "-m", "imssr", "sweep", "--no-progress", *args],
                          capture_output=True, text=True, timeout=300)
    if check and proc.returncode != 0:
        raise AssertionError(f"imssr sweep failed:\n{proc.stdout}\n{proc.stderr}")
    return proc


def set_args(overrides):
    return [a for o in overrides for a in ("--set", o)]


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
    # Each run's config: its grid point on the preset.
    run = runs[4]
    built = run.resolved_config(cfg)
    assert (built.algo, built.env.task) == ("im-curl", "walker_walk")
    assert (built.intrinsic.beta0, built.train.seed, built.train.steps) == (0.05, 1, 500_000)
    # Without a beta sweep: the preset's beta_0 and no extra level.
    plain = expand(SweepConfig(root=str(tmp_path), algos=["im-curl"], tasks=[TASK], seeds=[3]))
    assert [os.path.relpath(r.dir, tmp_path) for r in plain] == [f"{TASK}/im-curl/seed_3"]
    assert plain[0].resolved_config(cfg).intrinsic.beta0 == 0.01


def test_the_worker_trains_the_config_the_sweep_writes(tmp_path):
    """The run's config.json is its one description: `imssr train --config RUN/config.json` builds
    exactly it, and it is what `imssr train` builds from the sweep's settings as flags (seed,
    budget, beta_0, the GPU share as the device, --cpus-per-run as the torch threads)."""
    flags = {"im-soda": ["--algo", "im-soda", "--task", "finger_spin", "--seed", "4", "--steps", "50", "--beta0",
                         "0.2", "--device", "cuda", "--set", "train.torch_threads=2",
                         "--set", "agent.batch_size=8", "--set", "train.eval_episodes=2",
                         "--set", "train.gpu_share=0.5"],
             "curl+rnd": ["--algo", "curl+rnd", "--task", TASK, "--seed", "1", "--frames", "3001",
                          "--set", "train.torch_threads=1"]}
    for cfg in [SweepConfig(root=str(tmp_path), algos=["im-soda"], tasks=["finger_spin"], seeds=[4], steps=50,
                            beta0=[0.2], gpus_per_run=0.5, cpus_per_run=2.5,
                            overrides=["agent.batch_size=8", "train.eval_episodes=2"]),
                SweepConfig(root=str(tmp_path), algos=["curl+rnd"], tasks=[TASK], seeds=[1], frames=3001)]:
        for run in expand(cfg.validate()):
            built = run.resolved_config(cfg)
            path = RunDir(run.dir).write_config(built)
            assert cli_config("--config", path, "--out", run.dir) == built
            assert cli_config(*flags[run.algo], "--out", run.dir) == built
            assert built.train.device == ("cuda" if cfg.gpus_per_run else "cpu")
            # Progress on: the worker writes into sweep.log, a progress line a minute.
            assert (built.train.torch_threads, built.train.progress) == (max(1, int(cfg.cpus_per_run)), True)


def test_run_arguments_and_done_marker(tmp_path):
    cfg = SweepConfig(root=str(tmp_path), algos=["curl"], tasks=[TASK], seeds=[2], steps=375,
                      gpus_per_run=0.5, overrides=["agent.batch_size=8"])
    (run,) = expand(cfg)
    # A GPU share means training on it, unless the overrides choose a device.
    built = run.resolved_config(cfg)
    assert (built.algo, built.env.task, built.train.seed, built.train.steps) == ("curl", TASK, 2, 375)
    assert (built.train.device, built.agent.batch_size) == ("cuda", 8)
    # Half a GPU each: the run places its replay frames within half of the GPU's memory.
    assert built.train.gpu_share == 0.5
    whole = replace(cfg, gpus_per_run=1.0)
    assert expand(whole)[0].resolved_config(whole).train.gpu_share == 1.0
    cfg.overrides.append("train.device=cuda:1")
    assert run.resolved_config(cfg).train.device == "cuda:1"
    # The budget in frames instead: `imssr train --frames` turns it into the task's agent steps.
    by_frames = SweepConfig(root=str(tmp_path), algos=["curl"], tasks=[TASK], seeds=[2], frames=3000)
    assert run.resolved_config(by_frames).train.steps == 375  # 3000 / 8 rounded up
    os.makedirs(run.dir)
    files = RunDir(run.dir)
    assert not files.is_done(375)
    with open(os.path.join(run.dir, "eval.csv"), "w") as fh:
        fh.write("frame,step,mode,return_mean\n1000,125,training,1.5\n3000,375,training,2.5\n3")  # cut short
    assert files.last_evaluation() == (375, 3000)
    files.write_done(375, 375, attempt=1, resumed=False, seconds=12.5)
    assert (files.read_done()["steps"], files.read_done()["final_frame"]) == (375, 3000)
    assert files.is_done(375) and files.is_done(250)
    (status,) = plan_runs(cfg)  # a later sweep over the root: skipped, its time still reported
    assert (status.state, status.steps, status.frames) == ("done", 375, 3000)
    assert (status.final_step, status.final_frame, status.seconds) == (375, 3000, 12.5)
    assert not files.is_done(376)  # a larger budget resumes the finished run
    with open(os.path.join(run.dir, DONE_FILE), "w") as fh:
        fh.write('{"steps": 37')  # torn marker: not done
    assert not files.is_done(375)


AUTOGROUP_SCRIPT = """
import os, sys
from imssr.sweep.runner import start_training
n = os.nice(7); ps = []
log = open(sys.argv[1], 'w')
try:
    for niceness in (n, n, 0):  # two niced starts in a row meet the kernel's rate limit
        ps.append(start_training(['sleep', '30'], log, dict(os.environ), niceness))
    groups = [open(f'/proc/{p.pid}/autogroup').read().split() for p in ps]
    if not all(groups):
        sys.exit(3)  # a new session got no autogroup: nothing to check here
    print(n, all(os.getsid(p.pid) == p.pid for p in ps), *(f'{g[0]}:{g[2]}' for g in groups))
finally:
    for p in ps: p.kill()
"""


@pytest.mark.skipif(not (os.access("/proc/self/autogroup", os.W_OK) and autogroup_scheduling()),
                    reason="no Linux autogroup scheduling")
@pytest.mark.parametrize("caps", ["as is", "without CAP_SYS_ADMIN"])
def test_a_niced_sweep_starts_niced_trainings_across_session_groups(caps, tmp_path):
    """A training runs in a session of its own (so that stopping it signals its process group);
    under autogroup scheduling its nice value would count only inside that session, so the
    session's group gets the nice value of the sweep that started it.  Niceness 0 (a plain
    sweep, whatever its Ray worker's own +15) leaves the group at its default.  Without
    CAP_SYS_ADMIN the kernel refuses a second change within 0.1 s (EAGAIN): starts wait."""
    log = tmp_path / "sweep.log"
    cmd = [sys.executable, "-c", AUTOGROUP_SCRIPT, str(log)]
    if caps != "as is":
        drop = ["setpriv", "--bounding-set=-sys_admin", "--inh-caps=-sys_admin"]
        if shutil.which("setpriv") is None or subprocess.run([*drop, "true"]).returncode != 0:
            pytest.skip("needs setpriv, allowed to drop CAP_SYS_ADMIN")
        cmd = [*drop, *cmd]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    if out.returncode == 3:
        pytest.skip("new sessions get no autogroup here")
    assert out.returncode == 0, out.stderr
    niceness, own_sessions, *groups = out.stdout.split()
    assert own_sessions == "True"
    (first, n1), (second, n2), (plain, n0) = (g.split(":") for g in groups)
    parent = autogroup()  # None in the boot-time group
    assert len({first, second, plain}) == 3 and not (parent and parent[0] in {first, second, plain})
    assert n1 == n2 == niceness, log.read_text()  # 7 above the test's own; else the warning says why
    assert n0 == "0"


def test_ray_trainings_get_the_sweeps_priority_not_the_workers(tmp_path):
    from imssr.sweep.launchers import sweep_niceness

    assert sweep_niceness(SweepConfig(root=str(tmp_path), algos=["curl"], tasks=[TASK])) == os.nice(0)
    cluster = SweepConfig(root=str(tmp_path), algos=["curl"], tasks=[TASK], address="10.0.0.1:6379")
    assert sweep_niceness(cluster) is None


def test_sweep_file_equals_flags(tmp_path, capsys):
    path = tmp_path / "sweep.json"
    path.write_text(json.dumps({"algos": ["curl", "im-curl"], "tasks": TASK, "seeds": "1-2", "steps": 250,
                                "set": TINY, "retries": 3, "root": str(tmp_path / "r")}))
    from_file = load_sweep_file(str(path)).validate()
    assert (from_file.seeds, from_file.steps, from_file.retries, from_file.overrides) == ([1, 2], 250, 3, TINY)
    assert main(["sweep", "--file", str(path), "--dry-run"]) == 0
    by_file = capsys.readouterr().out
    assert main(["sweep", "--algos", "curl,im-curl", "--tasks", TASK, "--seeds", "1,2", "--steps", "250",
                 "--root", str(tmp_path / "r"), *set_args(TINY), "--dry-run"]) == 0
    assert capsys.readouterr().out == by_file
    assert by_file.startswith(f"4 runs under {tmp_path / 'r'}:")
    assert f"{TASK}/im-curl/seed_2\tim-curl {TASK} seed 2, 250 agent steps (2,000 frames)\t[new]" in by_file
    # The same budget in frames, from the file or a flag; a flag's budget replaces the file's.
    path.write_text(json.dumps({"algos": ["curl", "im-curl"], "tasks": TASK, "seeds": "1-2", "frames": 2000,
                                "set": TINY, "retries": 3, "root": str(tmp_path / "r")}))
    assert main(["sweep", "--file", str(path), "--dry-run"]) == 0
    assert capsys.readouterr().out.replace("--frames 2000", "--steps 250") == by_file
    assert main(["sweep", "--file", str(path), "--steps", "250", "--dry-run"]) == 0
    assert capsys.readouterr().out == by_file
    assert not (tmp_path / "r").exists()  # a dry run creates nothing


def test_every_sweep_setting_is_a_flag_made_from_its_field(capsys):
    """`imssr sweep`'s flags are SweepConfig's fields: each is `--` and its sweep-file key, its help
    the field's docstring and its default, its value checked as the field's type, and the value
    given is the field's."""
    text = cli_help("sweep")
    entries = {flag: (metavar, help_text) for flag, metavar, help_text in
               re.findall(r"^  (--[\w-]+)( \S+)?(.*(?:\n {5,}\S.*)*)", text, flags=re.M)}
    docs = dataclass_field_docs(SweepConfig)
    for field in fields(SweepConfig):
        flag = "--" + setting_key(field.name).replace("_", "-")
        assert flag in entries, f"no flag for SweepConfig.{field.name}"
        help_text = " ".join(entries[flag][1].split())
        assert help_text.startswith(docs[field.name].replace("``", "")) and "(default: " in help_text, help_text
        assert setting_key(field.name) in entries["--file"][1]  # a sweep file's keys
    assert "0: 24 hours. A run cut by the limit is retried from its last checkpoint. (default: 0)" in \
        " ".join(entries["--slurm-time"][1].split())
    for args, message in ((["--slurm-time", "1.5"], "argument --slurm-time: expected an integer >= 0, got '1.5'"),
                          (["--cpus-per-run", "0"], "argument --cpus-per-run: expected a number > 0, got '0'")):
        with pytest.raises(SystemExit):
            main(["sweep", *args])
        assert capsys.readouterr().err.strip() == f"imssr: error: {message} (see imssr sweep --help)"
    given = ["--root", "r", "--algos", "im-curl", "--tasks", TASK, "--seeds", "1-2", "--steps", "5", "--set",
             "agent.batch_size=8", "--beta0", "0.1", "--retries", "2", "--cpus-per-run", "1.5", "--gpus-per-run", "0.5",
             "--max-parallel", "3", "--runs-per-process", "2", "--launcher", "slurm", "--slurm-partition", "p",
             "--slurm-time", "9", "--slurm-gpus-per-task", "1", "--slurm-array-parallelism", "4", "--logger", "csv"]
    cfg = _sweep_config(build_parser().parse_args(["sweep", *given]))
    assert cfg == SweepConfig(root="r", algos=["im-curl"], tasks=[TASK], seeds=[1, 2], steps=5,
                              overrides=["agent.batch_size=8"], beta0=[0.1], retries=2, cpus_per_run=1.5,
                              gpus_per_run=0.5, max_parallel=3, runs_per_process=2, launcher="slurm",
                              slurm_partition="p", slurm_time=9, slurm_gpus_per_task=1, slurm_array_parallelism=4,
                              logger="csv")
    # Every field but the two that exclude another given here (frames: steps; address: slurm).
    assert [f.name for f in fields(SweepConfig) if getattr(cfg, f.name) == getattr(SweepConfig(), f.name)] == \
        ["frames", "address"]


@pytest.mark.parametrize("args, message", [
    (["--algos", "curl,drq", "--tasks", TASK], "unknown algo 'drq'"),
    (["--algos", "curl", "--tasks", "cartpole_swingup_sparce"], "unknown task 'cartpole_swingup_sparce'"),
    (["--algos", "curl", "--tasks", TASK, "--seeds", "1,x"], "bad seeds 'x'"),
    (["--algos", "curl", "--tasks", TASK, "--seeds", "5-2"], "bad seed range '5-2'"),
    (["--algos", "curl", "--tasks", TASK, "--set", "agent.bogus=1"], "unknown setting 'agent.bogus'"),
    (["--algos", "curl", "--tasks", TASK, "--beta0", "0.1"], "--beta0 needs an algo with an intrinsic reward"),
    (["--algos", "im-curl", "--tasks", TASK, "--beta0", "0.1,-1"], "beta0 values must be >= 0"),
    (["--algos", "im-curl", "--tasks", TASK, "--beta0", "0.1,inf"], "beta0 values must be >= 0 and finite"),
    # imssr train's seed rule: a seed it refuses would pass here and fail every run.
    (["--algos", "curl", "--tasks", TASK, "--seeds", "1,18446744073709551616"],
     "seeds must be an integer in [0, 2147483647] (numpy and dm_control take 32-bit seeds, and evaluation "
     "adds up to 20000), got 18446744073709551616"),
    (["--algos", "curl", "--tasks", TASK, "--seeds", "4294967296"], "seeds must be an integer in [0, 2147483647]"),
    (["--algos", "curl", "--tasks", TASK, "--set", "train.seed_steps=1e30"], "train.seed_steps must be at most 2,147,483,647"),
    # What the grid sets per run is not overridden for every run (each would train seed 5).
    (["--algos", "curl", "--tasks", TASK, "--seeds", "1-2", "--set", "train.seed=5"],
     "--set train.seed is set by the sweep's grid for every run (--seeds); leave it out of --set"),
    (["--algos", "im-curl", "--tasks", TASK, "--beta0", "0.1,0.2", "--set", "intrinsic.beta0=0.3"],
     "--set intrinsic.beta0 is set by the sweep's grid for every run (--beta0)"),
    (["--algos", "curl", "--tasks", TASK, "--steps", "100", "--set", "train.steps=50"],
     "--set train.steps is set by the sweep's grid for every run (--steps/--frames)"),
    # An empty root is not the current directory.
    (["--algos", "curl", "--tasks", TASK, "--root", ""],
     "the sweep's root is empty: give --root DIR (or \"root\" in the sweep file)"),
    # A range is checked before its seeds are listed.
    (["--algos", "curl", "--tasks", TASK, "--seeds", "5-3000000000"],
     "bad seed range '5-3000000000': 2,999,999,996 seeds, at most 100,000"),
    (["--algos", "curl", "--tasks", TASK, "--set", "agent.critic_lr=NaN"], "agent.critic_lr expects a finite number"),
    (["--tasks", TASK], "a sweep needs --algos"),
    (["--algos", "curl", "--tasks", TASK, "--steps", "10", "--frames", "80"],
     "give the budget as --steps (agent steps) or --frames, not both"),
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


def test_steps_and_frames_together_is_a_one_line_error(tmp_path):
    proc = sweep_cli("--steps", "10", "--frames", "80", check=False)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines() == \
        ["imssr: error: give the budget as --steps (agent steps) or --frames, not both"]
    # ... and so in a sweep file.
    path = tmp_path / "sweep.json"
    path.write_text(json.dumps({"algos": "curl", "tasks": TASK, "steps": 10, "frames": 80}))
    proc = sweep_cli("--file", str(path), "--dry-run", check=False)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == \
        ["imssr: error: give the budget as --steps (agent steps) or --frames, not both"]


def test_bad_input_has_no_traceback():
    proc = sweep_cli("--algos", "drq", "--tasks", TASK, check=False)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1].startswith("imssr: error: unknown algo 'drq'")


def test_sweep_resumes_interrupted_run_skips_finished_and_reports(tmp_path):
    """Two runs on local Ray: one interrupted beforehand (resumed), one fresh; a re-run starts nothing."""
    from imssr.training import Trainer

    root = str(tmp_path / "sweep")
    grid = ["--root", root, "--algos", "curl,im-curl", "--tasks", TASK, "--seeds", "1", "--steps", "250",
            *set_args(TINY)]
    cfg = SweepConfig(root=root, algos=["curl", "im-curl"], tasks=[TASK], seeds=[1], steps=250, overrides=TINY)
    interrupted = expand(cfg)[1]
    # The im-curl run was stopped at its first checkpoint (agent step 125 of 250, an episode end).  One torch
    # thread, as the sweep gives each run: two spin-waiting threads on a busy 2-core machine
    # are ~15x slower.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    trainer = Trainer(interrupted.resolved_config(cfg), interrupted.dir)
    try:
        train_stopped_at(trainer, 125)
    finally:
        trainer.close()
        torch.set_num_threads(threads)
    first_episode = read_csv(os.path.join(interrupted.dir, "train.csv"))[0]

    proc = sweep_cli(*grid)
    assert "2 runs, 0 done, 1 to resume, 1 new" in proc.stdout
    runs = {r["algo"]: r for r in sweep_status(root)["runs"]}
    assert sweep_status(root)["counts"] == {"queued": 0, "running": 0, "done": 2, "failed": 0, "interrupted": 0}
    assert (runs["im-curl"]["action"], runs["curl"]["action"]) == ("resume", "fresh")
    assert runs["im-curl"]["attempts"] == runs["curl"]["attempts"] == 1
    assert (runs["curl"]["steps"], runs["curl"]["frames"], runs["curl"]["final_step"]) == (250, 2000, 250)
    for run in expand(cfg):
        evals = read_csv(os.path.join(run.dir, "eval.csv"))
        assert [(int(r["step"]), int(r["frame"])) for r in evals] == [(125, 1000), (250, 2000)]
        with open(os.path.join(run.dir, DONE_FILE)) as fh:
            done = json.load(fh)
        assert (done["steps"], done["frames"], done["final_step"], done["final_frame"]) == (250, 2000, 250, 2000)
    assert {(p.steps, p.frames, p.precision) for p in SweepDir(root).read_plan()} == {(250, 2000, "fp32")}
    # Resumed, not restarted: the episode logged before the interruption is kept as it was.
    assert read_csv(os.path.join(interrupted.dir, "train.csv"))[0] == first_episode
    assert "(resume)" in open(os.path.join(interrupted.dir, SWEEP_LOG)).read()

    # Idempotence: a finished sweep starts nothing (no Ray, no attempt, no file touched).
    logs = {run.dir: open(os.path.join(run.dir, SWEEP_LOG)).read() for run in expand(cfg)}
    mtimes = {run.dir: os.path.getmtime(os.path.join(run.dir, "eval.csv")) for run in expand(cfg)}
    proc = sweep_cli(*grid)
    assert "all 2 runs are done; nothing to start" in proc.stdout
    assert {r["state"] for r in sweep_status(root)["runs"]} == {"done"}
    assert all(r["attempts"] == 0 for r in sweep_status(root)["runs"])
    for run in expand(cfg):
        assert open(os.path.join(run.dir, SWEEP_LOG)).read() == logs[run.dir]
        assert os.path.getmtime(os.path.join(run.dir, "eval.csv")) == mtimes[run.dir]

    # The report reads the sweep back: one seed each, the final evaluation at T = 250 agent steps.
    from imssr.report.report import write_report

    write_report(root, str(tmp_path / "report"), reps=50)
    final = {r["label"]: r for r in read_csv(tmp_path / "report" / "table.csv") if r["fraction"] == "1.0"}
    for run in expand(cfg):
        last = read_csv(os.path.join(run.dir, "eval.csv"))[-1]
        assert float(final[run.algo]["mean"]) == pytest.approx(float(last["return_mean"]))
        assert (final[run.algo]["step"], final[run.algo]["frame"], final[run.algo]["seeds"]) == ("250", "2000", "1")


def test_failing_run_is_retried_then_reported(tmp_path):
    root = str(tmp_path / "sweep")
    # Valid as a config, fails when the run starts: no such device.
    proc = sweep_cli("--root", root, "--algos", "curl", "--tasks", TASK, "--seeds", "4", "--steps", "125",
                     "--retries", "2", *set_args(TINY + ["train.device=cuda:99"]), check=False)
    assert proc.returncode == 1
    assert "1 of 1 runs failed after retries (curl cartpole_swingup_sparse seed 4)" in proc.stderr
    (run,) = sweep_status(root)["runs"]
    assert (run["state"], run["attempts"], len(run["errors"])) == ("failed", 3, 3)
    assert all("cuda:99" in e for e in run["errors"]), run["errors"]
    log = open(os.path.join(root, run["log"])).read()
    assert [line.split(" (")[0] for line in log.splitlines() if line.startswith("==> attempt")] == \
           ["==> attempt 1", "==> attempt 2", "==> attempt 3"]
    assert not os.path.exists(os.path.join(root, os.path.dirname(run["log"]), DONE_FILE))


def test_status_and_done_files_are_strict_json(tmp_path):
    """No bare NaN / Infinity in the JSON files a sweep writes (strict parsers refuse them)."""
    from imssr.sweep.directory import RunStatus

    def strict(path):
        with open(path) as fh:
            return json.load(fh, parse_constant=lambda name: pytest.fail(f"{path} holds {name}"))

    cfg = SweepConfig(root=str(tmp_path), algos=["curl"], tasks=[TASK], seeds=[1]).validate()
    (run,) = expand(cfg)
    st = RunStatus(run, 10, 80, seconds=float("nan"))
    assert strict(SweepDir(cfg.root).write_status([st], started=0.0, retries=cfg.retries))["runs"][0]["seconds"] is None
    os.makedirs(run.dir)
    RunDir(run.dir).write_done(10, 10, 1, False, seconds=float("inf"))
    assert strict(os.path.join(run.dir, DONE_FILE))["seconds"] is None


def _one_run(tmp_path, *overrides, retries=3):

    cfg = SweepConfig(root=str(tmp_path / "sweep"), algos=["curl"], tasks=[TASK], seeds=[3], steps=125,
                      overrides=TINY + list(overrides), retries=retries)
    return cfg, plan_runs(cfg)[0]


def test_a_diverged_run_is_not_retried_and_the_status_says_so(tmp_path):
    cfg, st = _one_run(tmp_path, "agent.critic_lr=1e30")
    RunDir(st.run.dir).write_config(st.config)  # as the sweep does before the first attempt
    result = execute_runs([st.run.dir], st.steps, 1)[0]
    assert result["diverged"] and not result["interrupted"], result
    assert RunDir(st.run.dir).status() == "diverged"
    line = settle(st, result, cfg.retries)
    assert st.state == "failed" and len(st.errors) == 1, line  # with 3 retries left
    assert "not retried: it diverges again" in line
    SweepDir(cfg.root).write_status([st], 0.0, cfg.retries)
    run = sweep_status(cfg.root)["runs"][0]
    assert run["state"] == "failed" and run["note"].startswith("diverged; not retried")
    assert "diverged at agent step" in run["errors"][0]


def test_a_run_with_only_numbered_checkpoints_resumes(tmp_path):
    cfg, st = _one_run(tmp_path)
    RunDir(st.run.dir).save_checkpoint(a_checkpoint(step=5), keep=1)
    os.unlink(RunDir(st.run.dir).latest)  # lost; step-000000005.pt is what --resume falls back to
    assert RunDir(st.run.dir).has_checkpoint()
    from imssr.sweep.sweep import plan_runs
    assert plan_runs(cfg)[0].action == "resume"


def _finished_without_checkpoint(run_dir: str, done: bool) -> dict[str, bytes]:
    """A run that finished (done.json from a sweep, or status.json from a training) and whose
    checkpoints the user deleted; returns its files' bytes."""
    run = RunDir(run_dir)
    run.write_config(tiny_config("curl", steps=125))
    files = {"train.csv": b"frame,step\n1000,125\n", "eval.csv": b"frame,step\n1000,125\n",
             "evaluate.csv": b"frame,step\n1000,125\n", "analysis/saliency.png": b"png",
             "videos/eval.mp4": b"mp4"}
    for name, data in files.items():
        os.makedirs(os.path.dirname(run.file(name)), exist_ok=True)
        with open(run.file(name), "wb") as fh:
            fh.write(data)
    if done:
        run.write_done(125, 125, 1, False)
    else:
        run.write_status("finished", 125)
    return {name: open(run.file(name), "rb").read() for name in [*files, "done.json" if done else "status.json"]}


@pytest.mark.parametrize("done", [True, False], ids=["done.json", "status"])
def test_a_fresh_attempt_never_deletes_a_finished_run_without_checkpoint(tmp_path, done):
    """The budget grew, the checkpoints are gone: the attempt fails in one line and keeps every file."""
    from imssr.sweep.runner import RunAttempt

    run_dir = str(tmp_path / "run")
    before = _finished_without_checkpoint(run_dir, done)
    attempt = RunAttempt(run_dir, 250, 1)
    assert attempt.proc is None and not attempt.resumed
    assert attempt.error == (f"{run_dir} holds a finished run without a checkpoint; move it away to train "
                             "it again")
    assert {name: open(os.path.join(run_dir, name), "rb").read() for name in before} == before
    result = attempt.finish()
    assert not result["ok"] and result["error"] == attempt.error
    assert RunDir(run_dir).status() == "finished"


def test_a_fresh_attempt_keeps_results_only_a_checkpoint_makes_and_a_run_in_use(tmp_path, monkeypatch):
    """evaluate.csv without a checkpoint (deleted) is a run too; a directory another process holds
    is not cleared under it.  What a training left before its first checkpoint is."""
    from imssr.sweep import runner
    from imssr.sweep.runner import RunAttempt

    monkeypatch.setattr(runner, "WRITER_WAIT_S", 0.0)  # the holder below never lets go while it waits

    run_dir = str(tmp_path / "run")
    run = RunDir(run_dir)
    run.write_config(tiny_config("curl", steps=125))
    for name in ("train.csv", "evaluate.csv"):
        with open(run.file(name), "w") as fh:
            fh.write("frame,step\n1000,125\n")
    attempt = RunAttempt(run_dir, 125, 1)
    assert attempt.proc is None
    assert attempt.error == (f"{run_dir} holds results of a run without a checkpoint (evaluate.csv); move it "
                             "away to train it again")
    assert os.path.exists(run.train_log) and os.path.exists(run.evaluate_log)
    os.unlink(run.evaluate_log)
    lock = run.open()
    try:
        attempt = RunAttempt(run_dir, 125, 1)
        assert attempt.proc is None and f"{run_dir} is in use by PID {os.getpid()}" in attempt.error
        assert os.path.exists(run.train_log)
    finally:
        lock.release()
    assert run.discard_unresumable() == ["train.csv"]
    assert not os.path.exists(run.train_log) and run.has_config()


def test_runs_that_can_share_a_batch_are_packed_into_processes(tmp_path):
    from imssr.sweep.sweep import pack

    cfg = SweepConfig(root=str(tmp_path / "s"), algos=["curl", "im-curl", "curl+rnd"], tasks=[TASK], seeds=[1, 2],
                      steps=125, overrides=TINY)
    queued = plan_runs(cfg)
    names = lambda groups: [[st.run.name for st in g] for g in groups]  # noqa: E731
    assert all(len(g) == 1 for g in pack(queued, 1))  # the default: one run per process, CPU or CUDA
    assert names(pack(queued, 3)) == [
        [f"curl {TASK} seed 1", f"curl {TASK} seed 2", f"im-curl {TASK} seed 1"],
        [f"im-curl {TASK} seed 2"],
        [f"curl+rnd {TASK} seed 1", f"curl+rnd {TASK} seed 2"]]  # RND's own weights: a batch of its own
    statuses = plan_runs(replace(cfg, algos=["curl", "im-curl"]))
    assert [len(g) for g in pack(statuses, 0)] == [4]  # 0: all that can share
    fused = plan_runs(replace(cfg, algos=["curl"], overrides=TINY + ["agent.update_schedule=fused"]))
    assert [len(g) for g in pack(fused, 3)] == [2]  # either schedule trains in a batch
    compiled = plan_runs(replace(cfg, algos=["curl"], overrides=TINY + ["agent.compile=default"]))
    assert [len(g) for g in pack(compiled, 3)] == [1, 1]  # a setting no batch takes: a process each


def test_a_dry_run_shows_which_runs_train_in_one_process(tmp_path, capsys):
    root = tmp_path / "s"
    args = ["sweep", "--algos", "curl,im-curl,curl+rnd", "--tasks", TASK, "--seeds", "1,2", "--steps", "125",
            "--root", str(root), *set_args(TINY), "--dry-run"]
    assert main([*args, "--runs-per-process", "3"]) == 0
    out = capsys.readouterr().out.splitlines()
    start = out.index("6 runs to train in 3 processes, one line each (imssr train --runs):")
    assert out[start + 1:start + 4] == [  # as pack() groups them (RND's own weights: a batch of its own)
        f"  {TASK}/curl/seed_1 {TASK}/curl/seed_2 {TASK}/im-curl/seed_1",
        f"  {TASK}/im-curl/seed_2",
        f"  {TASK}/curl+rnd/seed_1 {TASK}/curl+rnd/seed_2"], out
    assert main(args) == 0  # by default: a process each
    assert "6 runs to train, each in a process of its own" in capsys.readouterr().out.splitlines()


def test_a_packed_sweep_trains_curl_and_im_curl_in_one_process(tmp_path):
    root = str(tmp_path / "sweep")
    proc = sweep_cli("--algos", "curl,im-curl", "--tasks", TASK, "--seeds", "1", "--steps", "125",
                     "--root", root, "--launcher", "local", "--runs-per-process", "2", *set_args(TINY))
    assert "2 runs in 1 processes" in proc.stdout
    runs = sweep_status(root)["runs"]
    assert [r["state"] for r in runs] == ["done", "done"]
    second = os.path.join(root, runs[1]["log"])
    assert "trained in one process with 1 other run(s)" in open(second).read()
    for r in runs:
        assert RunDir(os.path.join(root, r["dir"])).is_done(125)


def test_a_packed_attempt_killed_by_a_signal_says_so_for_each_run(tmp_path):
    """Killed outright, the process wrote no status: each run's error is the signal, not the last
    line the process happened to print."""
    import signal

    from imssr.sweep.runner import RunAttempt

    dirs = [str(tmp_path / f"seed_{seed}") for seed in (1, 2)]
    for seed, d in zip((1, 2), dirs):
        RunDir(d).write_config(tiny_config("curl", seed=seed, steps=125))
    attempt = RunAttempt(dirs, 125, 1)
    try:
        while "in one process:" not in open(attempt.log_path).read():  # the training said something
            assert attempt.proc.poll() is None, open(attempt.log_path).read()
            time.sleep(0.2)
    finally:
        os.killpg(attempt.proc.pid, signal.SIGKILL)
    results = attempt.finish_all()
    assert [(r["ok"], r["interrupted"], r["error"]) for r in results] == [(False, False, "killed by signal 9 (SIGKILL)")] * 2
    assert [RunDir(d).read_status()["error"] for d in dirs] == ["killed by signal 9 (SIGKILL)"] * 2
