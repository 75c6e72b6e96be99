"""imssr sweep: grid expansion, input errors, and real sweeps on a local Ray (tiny budgets):
resume of an interrupted run, idempotence, retry accounting, and a report of the result."""
import json
import os
import subprocess
import sys

import pytest
import torch

from conftest import train_stopped_at
from imssr.cli import main
from imssr.sweep.grid import SweepConfig, build_run_config, expand, load_sweep_file, parse_seeds
from imssr.sweep.runner import DONE_FILE, LOG_FILE, execute_run, has_checkpoint
from imssr.sweep.sweep import plan_runs, settle, write_status
from imssr.training.checkpoint import latest_path, save_checkpoint
from imssr.training.logger import read_csv

TASK = "cartpole_swingup_sparse"  # 1000 frames = 125 agent steps per episode, action repeat 8
# The tiny settings of tests/conftest.py as overrides every run of a sweep gets (no 1000-update
# burst after the seed phase: the presets' DMC-GB burst would dominate a 250-step run).
TINY = ["train.seed_steps=60", "train.burst_updates=0", "agent.batch_size=8", "aux.batch_size=8",
        "agent.hidden_dim=32", "agent.feature_dim=16", "agent.encoder_filters=8", "train.replay_capacity=3000",
        "train.eval_every_steps=125", "train.eval_episodes=1", "train.checkpoint_every_steps=125",
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
    assert (built.intrinsic.beta0, built.train.seed, built.train.steps) == (0.05, 1, 500_000)
    # Without a beta sweep: the preset's beta_0 and no extra level.
    plain = expand(SweepConfig(root=str(tmp_path), algos=["im-curl"], tasks=[TASK], seeds=[3]))
    assert [os.path.relpath(r.dir, tmp_path) for r in plain] == [f"{TASK}/im-curl/seed_3"]
    assert build_run_config(plain[0], cfg).intrinsic.beta0 == 0.01


def test_a_sweep_run_config_is_what_imssr_train_builds_from_its_arguments(tmp_path):
    from imssr.cli import _run_config, build_parser

    for cfg in [SweepConfig(root=str(tmp_path), algos=["im-soda"], tasks=["finger_spin"], seeds=[4], steps=50,
                            beta0=[0.2], gpus_per_run=0.5, overrides=["agent.batch_size=8", "train.eval_episodes=2"]),
                SweepConfig(root=str(tmp_path), algos=["curl+rnd"], tasks=[TASK], seeds=[1], frames=3001)]:
        for run in expand(cfg.validate()):
            args = build_parser().parse_args(["train", *run.train_args(cfg), "--out", run.dir])
            built = build_run_config(run, cfg)
            assert built == _run_config(args, demo=False)
            assert built.train.device == ("cuda" if cfg.gpus_per_run else "cpu")


def test_run_arguments_and_done_marker(tmp_path):
    from imssr.sweep.runner import is_done, last_frame, last_step, read_done, write_done
    cfg = SweepConfig(root=str(tmp_path), algos=["curl"], tasks=[TASK], seeds=[2], steps=375,
                      gpus_per_run=0.5, overrides=["agent.batch_size=8"])
    (run,) = expand(cfg)
    # A GPU share means training on it, unless the overrides choose a device.
    assert run.train_args(cfg) == ["--algo", "curl", "--task", TASK, "--seed", "2", "--steps", "375",
                                   "--device", "cuda", "--set", "agent.batch_size=8"]
    cfg.overrides.append("train.device=cuda:1")
    assert "--device" not in run.train_args(cfg)
    # The budget in frames instead: `imssr train --frames` turns it into the task's agent steps.
    by_frames = SweepConfig(root=str(tmp_path), algos=["curl"], tasks=[TASK], seeds=[2], frames=3000)
    assert run.train_args(by_frames)[6:] == ["--frames", "3000"]
    assert build_run_config(run, by_frames).train.steps == 375  # 3000 / 8 rounded up
    os.makedirs(run.dir)
    assert not is_done(run.dir, 375)
    with open(os.path.join(run.dir, "eval.csv"), "w") as fh:
        fh.write("frame,step,mode,return_mean\n1000,125,training,1.5\n3000,375,training,2.5\n3")  # cut short
    assert (last_step(os.path.join(run.dir, "eval.csv")), last_frame(os.path.join(run.dir, "eval.csv"))) == (375, 3000)
    write_done(run.dir, 375, 375, attempt=1, resumed=False, seconds=12.5)
    assert (read_done(run.dir)["steps"], read_done(run.dir)["final_frame"]) == (375, 3000)
    assert is_done(run.dir, 375) and is_done(run.dir, 250)
    (status,) = plan_runs(cfg)  # a later sweep over the root: skipped, its time still reported
    assert (status.state, status.steps, status.frames) == ("done", 375, 3000)
    assert (status.final_step, status.final_frame, status.seconds) == (375, 3000, 12.5)
    assert not is_done(run.dir, 376)  # a larger budget resumes the finished run
    with open(os.path.join(run.dir, DONE_FILE), "w") as fh:
        fh.write('{"steps": 37')  # torn marker: not done
    assert not is_done(run.dir, 375)


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
    (["--algos", "curl", "--tasks", TASK, "--set", "train.seed=1e30"], "train.seed must be an integer in"),
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
    trainer = Trainer(build_run_config(interrupted, cfg), interrupted.dir)
    try:
        train_stopped_at(trainer, 125)
    finally:
        trainer.close()
        torch.set_num_threads(threads)
    first_episode = read_csv(os.path.join(interrupted.dir, "train.csv"))[0]

    proc = sweep_cli(*grid)
    assert "2 runs, 0 done, 1 to resume, 1 new" in proc.stdout
    runs = {r["algo"]: r for r in status(root)["runs"]}
    assert status(root)["counts"] == {"queued": 0, "running": 0, "done": 2, "failed": 0, "interrupted": 0}
    assert (runs["im-curl"]["action"], runs["curl"]["action"]) == ("resume", "fresh")
    assert runs["im-curl"]["attempts"] == runs["curl"]["attempts"] == 1
    assert (runs["curl"]["steps"], runs["curl"]["frames"], runs["curl"]["final_step"]) == (250, 2000, 250)
    for run in expand(cfg):
        evals = read_csv(os.path.join(run.dir, "eval.csv"))
        assert [(int(r["step"]), int(r["frame"])) for r in evals] == [(125, 1000), (250, 2000)]
        with open(os.path.join(run.dir, DONE_FILE)) as fh:
            done = json.load(fh)
        assert (done["steps"], done["frames"], done["final_step"], done["final_frame"]) == (250, 2000, 250, 2000)
    with open(os.path.join(root, "sweep.json")) as fh:
        assert {(r["steps"], r["frames"]) for r in json.load(fh)["runs"]} == {(250, 2000)}
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
    (run,) = status(root)["runs"]
    assert (run["state"], run["attempts"], len(run["errors"])) == ("failed", 3, 3)
    assert all("cuda:99" in e for e in run["errors"]), run["errors"]
    log = open(os.path.join(root, run["log"])).read()
    assert [line.split(" (")[0] for line in log.splitlines() if line.startswith("==> attempt")] == \
           ["==> attempt 1", "==> attempt 2", "==> attempt 3"]
    assert not os.path.exists(os.path.join(root, os.path.dirname(run["log"]), DONE_FILE))


def old_config(algo, task, seed, frames):
    """config.json as imssr 0.1 wrote it: no version, budgets and intervals in frames."""
    from imssr.presets import make_config

    data = make_config(algo, task).to_dict()
    del data["version"], data["agent"]["final_relu"], data["aux"]["own_batch"]
    train = data["train"]
    del train["steps"], train["eval_every_steps"], train["checkpoint_every_steps"]
    train.update(frames=frames, eval_every_frames=1000, checkpoint_every_frames=1000, seed=seed)
    for key in ("form", "unbiased_std", "norm_eps", "norm_rtol"):
        del data["intrinsic"][key]
    data["intrinsic"]["view"] = "independent"
    return data


def test_old_run_directories_are_done_and_reported_in_agent_steps(tmp_path):
    """A sweep made when budgets counted frames: config.json with train.frames (no version),
    done.json and sweep.json with frames.  2000 frames at action repeat 8 are 250 agent steps."""
    from imssr.report.report import write_report
    from imssr.sweep.runner import done_steps, is_done
    from imssr.sweep.sweep import plan_runs, run_sweep

    root = str(tmp_path / "sweep")
    cfg = SweepConfig(root=root, algos=["curl", "im-curl"], tasks=[TASK], seeds=[1], steps=250, overrides=TINY)
    runs = expand(cfg)
    plan = {"sweep": {"frames": 2000}, "runs": []}
    for i, run in enumerate(runs):
        os.makedirs(run.dir)
        with open(os.path.join(run.dir, "config.json"), "w") as fh:
            json.dump(old_config(run.algo, TASK, run.seed, 2000), fh)
        with open(os.path.join(run.dir, "eval.csv"), "w") as fh:  # the old loop: first step at or past each frame
            fh.write("frame,step,mode,return_mean,return_std,episodes,return_min,return_max,wall_time\n"
                     f"1000,125,training,{10 + i},0,1,0,0,0\n2000,250,training,{100 + i},0,1,0,0,0\n")
        with open(os.path.join(run.dir, DONE_FILE), "w") as fh:
            json.dump({"frames": 2000, "final_frame": 2000, "evaluations": 2, "attempt": 1, "resumed": False,
                       "seconds": 3.0, "finished": "2025-01-01T00:00:00"}, fh)
        plan["runs"].append({"algo": run.algo, "task": TASK, "seed": run.seed, "beta0": None, "frames": 2000,
                             "dir": os.path.relpath(run.dir, root)})
    with open(os.path.join(root, "sweep.json"), "w") as fh:
        json.dump(plan, fh)

    # Done: the old marker's 2000 frames are the 250 agent steps of the run's action repeat.
    assert done_steps(runs[0].dir) == 250
    assert is_done(runs[0].dir, 250) and not is_done(runs[0].dir, 251)
    # Without a readable config, the last evaluation's step stands in for the budget.
    os.rename(os.path.join(runs[0].dir, "config.json"), os.path.join(tmp_path, "config.json"))
    assert done_steps(runs[0].dir) == 250
    os.rename(os.path.join(tmp_path, "config.json"), os.path.join(runs[0].dir, "config.json"))

    # The report: T = 250 agent steps (from the old plan's frames), points in steps and frames.
    out = str(tmp_path / "report")
    write_report(root, out, paper_results=str(tmp_path / "none.csv"), reps=50)
    table = {(r["label"], r["fraction"]): r for r in read_csv(os.path.join(out, "table.csv"))}
    assert (table["curl", "1.0"]["step"], table["curl", "1.0"]["frame"], table["curl", "1.0"]["mean"]) == \
        ("250", "2000", "100")
    assert (table["im-curl", "0.5"]["step"], table["im-curl", "0.5"]["frame"], table["im-curl", "0.5"]["mean"]) == \
        ("125", "1000", "11")
    md = open(os.path.join(out, "report.md")).read()
    assert "### `training` (T = 250 agent steps)" in md
    assert f"| `{TASK}` | 8 | 50 steps (400 frames) | 125 steps (1,000 frames) | 250 steps (2,000 frames) |" in md
    assert "planned but not started" not in md
    evaluations = read_csv(os.path.join(out, "evaluations.csv"))
    assert {(r["step"], r["frame"]) for r in evaluations} == {("125", "1000"), ("250", "2000")}

    # A sweep over the old root, in steps or in frames, finds every run done and starts nothing.
    for budget in ({"steps": 250}, {"frames": 2000}):
        again = SweepConfig(root=root, algos=["curl", "im-curl"], tasks=[TASK], seeds=[1], overrides=TINY, **budget)
        statuses = plan_runs(again)
        assert [(s.state, s.steps, s.frames, s.final_step, s.seconds) for s in statuses] == \
            [("done", 250, 2000, 250, 3.0)] * 2
    assert [s.state for s in run_sweep(again, progress=False)] == ["done", "done"]  # no Ray started
    assert status(root)["counts"]["done"] == 2
    bigger = SweepConfig(root=root, algos=["curl"], tasks=[TASK], seeds=[1], overrides=TINY, steps=300)
    assert [s.action for s in plan_runs(bigger)] == ["fresh"]  # a larger budget is not done


def test_status_and_done_files_are_strict_json(tmp_path):
    """No bare NaN / Infinity in the JSON files a sweep writes (strict parsers refuse them)."""
    from imssr.sweep.runner import write_done
    from imssr.sweep.sweep import RunStatus, write_status

    def strict(path):
        with open(path) as fh:
            return json.load(fh, parse_constant=lambda name: pytest.fail(f"{path} holds {name}"))

    cfg = SweepConfig(root=str(tmp_path), algos=["curl"], tasks=[TASK], seeds=[1]).validate()
    (run,) = expand(cfg)
    st = RunStatus(run, 10, 80, seconds=float("nan"))
    assert strict(write_status(cfg, [st], started=0.0))["runs"][0]["seconds"] is None
    os.makedirs(run.dir)
    write_done(run.dir, 10, 10, 1, False, seconds=float("inf"))
    assert strict(os.path.join(run.dir, DONE_FILE))["seconds"] is None


def _one_run(tmp_path, *overrides, retries=3):

    cfg = SweepConfig(root=str(tmp_path / "sweep"), algos=["curl"], tasks=[TASK], seeds=[3], steps=125,
                      overrides=TINY + list(overrides), retries=retries)
    return cfg, plan_runs(cfg)[0]


def test_a_diverged_run_is_not_retried_and_the_status_says_so(tmp_path):
    cfg, st = _one_run(tmp_path, "agent.critic_lr=1e30")
    result = execute_run(st.run.dir, st.run.train_args(cfg), st.steps, 1)
    assert result["diverged"] and not result["interrupted"], result
    line = settle(st, result, cfg.retries)
    assert st.state == "failed" and len(st.errors) == 1, line  # with 3 retries left
    assert "not retried: it diverges again" in line
    write_status(cfg, [st], 0.0)
    run = status(cfg.root)["runs"][0]
    assert run["state"] == "failed" and run["note"].startswith("diverged; not retried")
    assert "diverged at agent step" in run["errors"][0]


def test_a_run_with_only_numbered_checkpoints_resumes(tmp_path):
    cfg, st = _one_run(tmp_path)
    save_checkpoint(st.run.dir, {"step": 5, "replay_file": None}, keep=1)
    os.unlink(latest_path(st.run.dir))  # lost; step-000000005.pt is what --resume falls back to
    assert has_checkpoint(st.run.dir)
    from imssr.sweep.sweep import plan_runs
    assert plan_runs(cfg)[0].action == "resume"
