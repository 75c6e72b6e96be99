"""Guards of a real training run: divergence stops in one line and keeps the last checkpoint,
resume says where it resumes and warns on another thread count, a smaller budget is refused,
progress lines for logs, and a bad image folder fails before the seed phase."""
import os
import re

import numpy as np
import pytest
import torch

from conftest import TORCH_THREADS, cli_config, tiny_config, tiny_sets, train_stopped_at
from imssr.errors import DivergedError, ImssrError
from imssr.training import Trainer
from imssr.rundir import RunDir
from imssr.rundir.checkpoint import load_checkpoint
from imssr.training.logger import read_csv

TASK = "cartpole_swingup_sparse"
# cartpole episodes are 1000 frames: at action repeat 50 an episode is 20 agent steps.
FAST = ["--steps", "60", "--seed-steps", "10", "--eval-every", "0", "--eval-episodes", "1",
        "--replay-capacity", "1000", "--no-progress", "--no-tensorboard", *tiny_sets(),
        "--set", "train.burst_updates=0", "--set", "env.action_repeat=50"]


def fast(algo="curl", **train):
    """tiny_config with 20-step episodes and a 10-step seed phase, checkpoints at episode ends."""
    cfg = tiny_config(algo, TASK, **{"steps": 60, "seed_steps": 10, "eval_every_steps": 0,
                                     "checkpoint_every_steps": 20, **train})
    cfg.env.action_repeat = 50
    return cfg


def critic_poisoned_at_step_25(t: Trainer, stop: bool = False) -> Trainer:
    """``t`` whose critic weights turn NaN just before the update of agent step 25 (after the
    checkpoint at the end of episode 1, agent step 20); ``stop``: a SIGTERM arrives in that step."""
    update = t.agent.update

    def poisoned(replay, step):
        if step == 25:
            with torch.no_grad():
                next(t.agent.nets.critic.parameters()).fill_(float("nan"))
            if stop:
                t.stop.signal_name = "SIGTERM"  # as StopRequest's handler records it
        return update(replay, step)

    t.agent.update = poisoned
    return t


def test_divergence_stops_in_one_line_and_keeps_the_last_good_checkpoint(tmp_path):
    out = str(tmp_path / "run")
    t = critic_poisoned_at_step_25(Trainer(fast(), out))
    try:
        # The action of step 26 is NaN (checked on the host before the simulator sees it); the
        # message names the first non-finite loss of the episode so far.
        with pytest.raises(DivergedError, match=r"^diverged at agent step 26: critic loss nan$"):
            t.train()
    finally:
        t.close()
    ckpt = load_checkpoint(RunDir(out).latest)
    assert ckpt.step == 20  # nothing saved after the divergence
    assert [int(r["step"]) for r in read_csv(f"{out}/train.csv")] == [20]
    resumed = Trainer(fast(), out, resume=True)  # the last good checkpoint loads and resumes
    try:
        assert resumed.step == 20 and all(torch.isfinite(p).all() for p in resumed.agent.nets.parameters())
    finally:
        resumed.close()


def test_a_stop_right_after_a_diverged_update_saves_nothing(tmp_path):
    """A stop request in the agent step whose update diverged, before any action is NaN: the
    checkpoint the stop would write is refused, the run's last checkpoint stays the good one."""
    out = str(tmp_path / "run")
    t = critic_poisoned_at_step_25(Trainer(fast(), out), stop=True)
    try:
        with pytest.raises(DivergedError, match=r"^diverged at agent step 26: critic loss nan$"):
            t.train()
    finally:
        t.close()
    assert load_checkpoint(RunDir(out).latest).step == 20
    # Nothing of the refused save is left: the replay files are those latest.pt names.
    run = RunDir(out)
    named = {os.path.basename(p) for p in run.replay_files(load_checkpoint(run.latest).replay_file)}
    assert {f for f in os.listdir(run.checkpoint_dir) if f.startswith("replay-")} == named


def test_a_non_finite_intrinsic_signal_stops_the_run_naming_the_signal(tmp_path):
    """The update does not look at r_int (no host sync); the loop's metrics check does, before
    the critic's loss that it poisons in the same update."""
    t = Trainer(fast("im-curl"), str(tmp_path / "run"))
    signal = t.agent.signal
    loss = signal.task_loss

    def poisoned(ctx):
        out = loss(ctx)
        return out.index_fill(0, torch.tensor([1]), float("nan")) if t.step == 25 else out

    signal.task_loss = poisoned
    try:
        # The poisoned update runs at agent step 25; the action of step 26 is NaN.
        with pytest.raises(DivergedError, match=r"^diverged at agent step 26: intrinsic reward "
                                                r"\(curl per-sample loss of o'\) nan$"):
            t.train()
    finally:
        t.close()


def test_divergence_in_evaluation_is_caught_before_the_simulator(tmp_path):
    t = Trainer(fast(eval_every_steps=15), str(tmp_path / "run"))
    act = t.agent.act
    t.agent.act = lambda obs, deterministic: (np.full(1, np.inf, np.float32) if deterministic
                                              else act(obs, deterministic))
    try:
        with pytest.raises(DivergedError, match=r"^diverged at agent step 15: evaluation action inf$"):
            t.train()
    finally:
        t.close()


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_a_real_diverging_run_is_one_line_that_the_sweep_records(precision, tmp_path):
    """critic_lr=1e6 diverges in its first updates (dm_control would end it in a 26-line
    PhysicsError traceback); a bf16 run (mixed precision) blows up in its first updates too and
    stops with the same line (measured: fp32 "actor loss nan", bf16 "aux loss nan" at agent
    step 11), which the sweep does not retry."""
    from imssr.rundir import SWEEP_LOG
    from imssr.sweep.runner import execute_runs

    run = tmp_path / "run"
    args = ["--algo", "curl", "--task", TASK, "--seed", "1", *FAST, "--set", "agent.critic_lr=1e6",
            "--set", f"agent.precision={precision}"]
    RunDir(run).write_config(cli_config(*args, "--out", str(run)))
    result = execute_runs([str(run)], 60, attempt=1)[0]
    assert not result["ok"] and result["returncode"] == 2 and result["diverged"]
    assert re.fullmatch(r"imssr: error: diverged at agent step \d+: [a-z ]+ (nan|inf|-inf)", result["error"]), result
    assert RunDir(run).status() == "diverged"
    log = (run / SWEEP_LOG).read_text()
    assert "Traceback" not in log and "PhysicsError" not in log


def test_more_torch_threads_than_cores_train_with_the_cores_and_say_so(tmp_path, capsys):
    """train.torch_threads past the cores this process may run on: threads that spin against each
    other are no faster and often many times slower, so the run takes the cores, in one line."""
    cores = len(os.sched_getaffinity(0))
    try:
        Trainer(fast(torch_threads=1000), str(tmp_path / "run")).close()
        assert torch.get_num_threads() == cores
    finally:
        torch.set_num_threads(TORCH_THREADS)
    said = [line for line in capsys.readouterr().out.splitlines() if "thread" in line]
    assert said[0] == (f"imssr: warning: train.torch_threads=1000 is more than the {cores} cores this process may "
                       f"run on: it trains with {cores} torch threads"), said


def test_resume_reports_its_step_warns_on_another_thread_count_and_refuses_a_smaller_budget(tmp_path, capsys):
    out = str(tmp_path / "run")
    try:
        t = Trainer(fast(steps=40, torch_threads=1), out)
        try:
            train_stopped_at(t, 20)
        finally:
            t.close()
        assert load_checkpoint(RunDir(out).latest).torch_threads == 1
        capsys.readouterr()
        config = (tmp_path / "run" / "config.json").read_text()
        with pytest.raises(ImssrError, match=r"already at agent step 20, past the budget of 15 steps asked for; "
                                             r"resume with --steps 20 or more"):
            Trainer(fast(steps=15, torch_threads=1), out, resume=True)
        assert (tmp_path / "run" / "config.json").read_text() == config  # not rewritten
        resumed = Trainer(fast(steps=40, torch_threads=2), out, resume=True)
        resumed.begin()
        resumed.close()
        said = capsys.readouterr().out
        assert "imssr: resuming from agent step 20 (frame 1,000) of 40" in said
        assert ("imssr: warning: this run was trained with 1 torch thread(s) and resumes with 2: it stays valid "
                "but is no longer bit-identical to an uninterrupted run (--set train.torch_threads=1 keeps it "
                "exact)") in said
        resumed = Trainer(fast(steps=40, torch_threads=1), out, resume=True)
        resumed.begin()
        resumed.close()
        assert "torch thread" not in capsys.readouterr().out
        # The numerics are the run's own: reports and exports group runs by them.
        bf16 = fast(steps=40, torch_threads=1)
        bf16.agent.precision = "bf16"
        with pytest.raises(ImssrError, match=r"trains at fp32 and a resume keeps its numerics \(agent.precision "
                                             r"differ\): reports group runs by them; train bf16 as a new run"):
            Trainer(bf16, out, resume=True)
        assert (tmp_path / "run" / "config.json").read_text() == config
    finally:
        torch.set_num_threads(TORCH_THREADS)


def test_progress_lines_when_stdout_is_not_a_terminal(tmp_path, capsys):
    from imssr.training.loop import PROGRESS_EVERY_S

    assert PROGRESS_EVERY_S == 60.0
    # Mostly the seed phase: two updates after the first episode.
    t = Trainer(fast(steps=22, seed_steps=20, checkpoint_every_steps=0, progress=True), str(tmp_path / "run"))
    t.progress_every_s = 0.0  # a line every agent step; pytest's captured stdout is no terminal
    try:
        t.train()
    finally:
        t.close()
    # The agent steps' lines (a phase's, the final checkpoint's, end in "so far").
    lines = [line for line in capsys.readouterr().out.splitlines() if "frames/s" in line]
    assert len(lines) == 22, lines
    pattern = (r"imssr: agent step \d+/22 \(\d+\.\d%\), [\d,]+ frames/s, ETA (\d+:\d\d:\d\d|after agent step 22), "
               r"last episode return (none yet|-?\d+\.\d)")
    assert all(re.fullmatch(pattern, line) for line in lines), lines
    # No estimate from the seed phase's rate: it comes once the updates have a rate.
    assert all("ETA after agent step 22," in line for line in lines[:21]), lines
    assert lines[-1].split("last episode return ")[1] != "none yet"  # after the first episode


def test_a_bad_image_folder_fails_when_the_trainer_is_built(tmp_path):
    folder = tmp_path / "images"
    folder.mkdir()
    (folder / "a.jpg").write_bytes(b"not a jpeg")
    cfg = fast("soda")
    cfg.aux.image_dir = str(folder)
    with pytest.raises(ImssrError, match=r"no readable images under .*images: all 1 .jpg/.jpeg/.png files failed"):
        Trainer(cfg, str(tmp_path / "run"))
