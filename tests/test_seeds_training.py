"""Many seeds in one process (``imssr train --seeds``): standard run directories, an exact
resume, a diverged seed stopped alone, and one-line errors."""
from __future__ import annotations

import contextlib
import csv
import errno
import io
import json
import os
import re
import subprocess
import sys

import pytest
import torch

from conftest import REPO, TORCH_THREADS, StopAtStep, cli_status, run_imssr, tiny_config, tiny_sets, without_timing
from imssr.errors import ImssrError
from imssr.rundir import RunDir
from imssr.training.seeds import SeedsTrainer
from imssr.training.stop import TrainingInterrupted

SEEDS = (1, 2, 3)

CASES = {
    # case: (each seed's algorithm, agent.cuda_graphs, the file of seed 3 whose n-th write a kill -9 cuts)
    "curl": (("curl",) * 3, False, ("step-000000150.pt", 1)),
    "im-curl": (("im-curl",) * 3, True, ("latest.pt", 2)),
    "soda": (("soda",) * 3, True, ("latest.pt", 2)),
    "curl+im-curl": (("curl", "im-curl", "curl"), False, ("step-000000150.pt", 1)),
}
"""The batches of ``--seeds 1-3`` each of whose seeds must be its run alone, killed at their second
checkpoint (step 150) and resumed: as seed 3 writes it (every run resumes from 125 and trains
on), or as it becomes seed 3's latest.pt (every run trained through, each resumes from 150)."""


def configs(case: str = "curl", steps: int = 150, algos=None, n: int = 2):
    """The configs of the first ``n`` seeds of ``case`` (the figures' batches: 3; other tests: 2)."""
    cfgs = []
    case_algos, graphs, _ = CASES[case]
    for algo, seed in zip((algos or case_algos)[:n], SEEDS):
        cfg = tiny_config(algo, seed=seed, steps=steps, seed_steps=60, burst_updates=5, eval_every_steps=75,
                          checkpoint_every_steps=125, torch_threads=TORCH_THREADS)
        cfg.agent.cuda_graphs = graphs
        cfgs.append(cfg)
    return cfgs


def runs(root, n: int = 2) -> list[str]:
    return [os.path.join(str(root), f"seed_{s}") for s in SEEDS[:n]]


def train_seeds(root, stop_at=None, resume=False, cfgs=None):
    cfgs = cfgs or configs()
    trainer = SeedsTrainer(cfgs, runs(root, len(cfgs)), resume=resume)
    try:
        if stop_at is not None:
            trainer.stop = StopAtStep(trainer, stop_at)
            for t in trainer.trainers:
                t.stop = trainer.stop
        return trainer.train()
    finally:
        trainer.close()


def rows(path: str) -> list[dict]:
    with open(path, newline="") as f:
        return without_timing(list(csv.DictReader(f)))


def final_nets(run: str) -> dict[str, torch.Tensor]:
    return RunDir(run).checkpoint().checkpoint.agent["nets"]


def assert_same_run(run: str, other: str) -> None:
    """Every CSV value (but the timings) and every final weight of ``run`` are ``other``'s."""
    for log in ("train.csv", "eval.csv"):
        assert rows(os.path.join(run, log)) == rows(os.path.join(other, log)), (run, log)
    theirs = final_nets(other)
    for key, value in final_nets(run).items():
        assert torch.equal(value, theirs[key]), (run, key)


@pytest.fixture(scope="module")
def alone(tmp_path_factory):
    """The run alone of a config, trained once in this module (runs of the same config share it)."""
    from conftest import train_run

    done: dict[str, str] = {}

    def run_of(cfg) -> str:
        key = json.dumps(cfg.to_dict(), sort_keys=True)
        if key not in done:
            done[key] = str(tmp_path_factory.mktemp("alone"))
            train_run(cfg, done[key])
        return done[key]

    return run_of


@pytest.fixture(scope="module")
def batches(tmp_path_factory):
    """The uninterrupted batch of a case (:data:`CASES`), trained once in this module: its root."""
    done: dict[str, str] = {}

    def batch_of(case: str) -> str:
        if case not in done:
            done[case] = str(tmp_path_factory.mktemp(case.replace("+", "_")))
            assert train_seeds(done[case], cfgs=configs(case, n=3)) == [None, None, None]
        return done[case]

    return batch_of


@pytest.fixture(scope="module")
def uninterrupted(batches):
    return batches("curl")


@pytest.fixture(scope="module", params=list(CASES))
def killed(request, tmp_path_factory):
    """A case's batch killed (SIGKILL) at its second checkpoint and resumed: the case, its root and
    what the resume said."""
    case, root = request.param, tmp_path_factory.mktemp(f"killed_{request.param.replace('+', '_')}")
    kill_at, time = CASES[case][2]
    killed_batch(root, os.path.join(runs(root, 3)[2], "checkpoints", kill_at), time, configs(case, n=3))
    said = io.StringIO()
    with contextlib.redirect_stdout(said):
        assert train_seeds(root, resume=True, cfgs=configs(case, n=3)) == [None, None, None]
    return case, str(root), said.getvalue()


def test_each_seed_is_a_standard_run(uninterrupted):
    for seed, run in zip(SEEDS, runs(uninterrupted, 3)):
        config = json.load(open(os.path.join(run, "config.json")))
        assert config["train"]["seed"] == seed
        assert json.load(open(os.path.join(run, "status.json")))["state"] == "finished"
        assert len(rows(os.path.join(run, "train.csv"))) == 1  # one 125-step episode of 150 steps
        assert [r["step"] for r in rows(os.path.join(run, "eval.csv"))] == ["75", "150"]
        assert RunDir(run).checkpoint().checkpoint.step == 150
    # The seeds learned apart: their own weights.
    a, b, _ = (final_nets(r) for r in runs(uninterrupted, 3))
    assert not torch.equal(a["critic.q.q1.0.weight"], b["critic.q.q1.0.weight"])


@pytest.mark.parametrize("case", ["curl", "curl+im-curl"])
def test_every_seed_of_a_batch_is_its_run_alone(case, batches, alone):
    """On the CPU the members run one after another: each seed of a CURL and a mixed CURL + IM-CURL
    batch leaves the logs and weights of ``imssr train --seed N`` of its config (the IM-CURL and
    SODA batches, with agent.cuda_graphs, train through uninterrupted before their kill below)."""
    for cfg, run in zip(configs(case, n=3), runs(batches(case), 3)):
        assert_same_run(run, alone(cfg))


def test_every_seed_of_a_batch_killed_at_a_later_checkpoint_resumes_as_its_run_alone(killed, alone):
    """Killed as seed 3 writes its checkpoint of step 150 (seeds 1 and 2 wrote theirs): every run
    resumes from 125; killed as seed 3 makes its copy of 150 its latest.pt (the others did): every
    run resumes from 150, seed 3 from its numbered copy.  Either way each seed ends as its run alone."""
    case, root, out = killed
    step = 125 if CASES[case][2][0].startswith("step-") else 150
    # Every run resumes from the same step: the batch says it once.
    assert out.count(f"imssr: resuming from agent step {step} ") == 1 and "resuming from agent step" not in \
        out.replace(f"imssr: resuming from agent step {step} ", "", 1), out
    if step == 150:  # seed 3 from its numbered copy, its latest.pt being of step 125
        assert f"imssr: seed 3: {runs(root, 3)[2]}: resuming from step-000000150.pt at agent step 150, the last " \
               "checkpoint every run of the batch completed (its latest.pt is of agent step 125)" in out, out
    for cfg, run in zip(configs(case, n=3), runs(root, 3)):
        assert_same_run(run, alone(cfg))


def test_a_stopped_batch_resumes_exactly_also_from_a_stacked_layout(uninterrupted, tmp_path, capsys):
    """Stopped in the middle of an episode and resumed, every seed's logs and weights are those
    of the uninterrupted batch; a saved config's retired stacked layout (``vmap``) resumes as the
    one batch, in one line."""
    with pytest.raises(TrainingInterrupted, match=r"^stopped at agent step 100 by SIGTERM; continue with: "
                                                  r"imssr train --seeds 1,2 --out .* --resume"):
        train_seeds(tmp_path, stop_at=100)
    cfgs = configs()
    for cfg in cfgs:
        cfg.agent.batch_layout = "vmap"
    capsys.readouterr()
    assert train_seeds(tmp_path, resume=True, cfgs=cfgs) == [None, None]
    assert capsys.readouterr().out.count("agent.batch_layout=vmap (stacked weights) resumes as the one batch") == 1
    assert_same_as_uninterrupted(uninterrupted, tmp_path)


def test_a_new_run_in_a_stacked_layout_is_refused_in_one_line(tmp_path):
    cfgs = configs()
    for cfg in cfgs:
        cfg.agent.batch_layout = "loop"
    with pytest.raises(ImssrError, match=r"^agent.batch_layout=loop \(stacked weights\) is not offered: measured, "
                                         r".*0.46-0.49x.*docs/performance.md\); use auto or streams$"):
        SeedsTrainer(cfgs, runs(tmp_path))
    assert os.listdir(tmp_path) == []


def test_a_diverged_seed_stops_alone_and_a_base_member_never_computes_an_intrinsic_reward(tmp_path, alone, capsys):
    """In a CURL + IM-CURL + CURL batch, seed 1's critic turns to NaN and seed 2's (IM-CURL)
    intrinsic signal does: each stops alone, before its first checkpoint,
    and says so in one line; seed 3, a base member, never computes an intrinsic reward and trains
    on as its run alone."""
    cfgs = configs("curl", algos=("curl", "im-curl", "curl"), n=3)
    trainer = SeedsTrainer(cfgs, runs(tmp_path, 3))
    try:
        with torch.no_grad():
            for name, value in trainer.trainers[0].agent.nets.named_parameters():
                if name.startswith("critic.q."):
                    value.fill_(float("nan"))
        signal = trainer.trainers[1].agent.signal
        signal.forward = lambda ctx, forward=signal.forward: forward(ctx) * float("nan")
        failed = trainer.train()
    finally:
        trainer.close()
    assert failed[2] is None and all(f.startswith("diverged at agent step") for f in failed[:2])
    said = [line for line in capsys.readouterr().out.splitlines() if "diverged" in line]
    assert said == [f"imssr: seed {seed}: {why}; it has no checkpoint, the other seeds go on"
                    for seed, why in zip(SEEDS, failed[:2])]
    statuses = [json.load(open(os.path.join(run, "status.json")))["state"] for run in runs(tmp_path, 3)]
    assert statuses == ["diverged", "diverged", "finished"]
    assert_same_run(runs(tmp_path, 3)[2], alone(cfgs[2]))


def test_a_batch_says_each_seeds_lines_with_its_seed_and_a_warning_of_every_seed_once(tmp_path, capsys):
    """Evaluation and progress lines name their seed; a warning every seed gives alike (here: the
    seed phase outlasts the budget, so no seed ever updates) comes once, as for a run alone."""
    cfgs = configs(steps=80)
    for cfg in cfgs:
        cfg.train.seed_steps, cfg.train.progress = 100, True
    trainer = SeedsTrainer(cfgs, runs(tmp_path))
    try:
        for t in trainer.trainers:
            t.progress_every_s = 0.0  # a progress line every agent step (stdout is no terminal here)
        assert trainer.train() == [None, None]
    finally:
        trainer.close()
    out = capsys.readouterr().out.splitlines()
    assert len([line for line in out if line.startswith("imssr: warning: the seed phase")]) == 1, out
    evaluations = [line for line in out if "eval step" in line]
    progress = [line for line in out if "frames/s" in line]
    for seed in SEEDS[:2]:
        assert f"seed {seed}: eval step 75 frame 600: return 0.0 ± 0.0" in evaluations, evaluations
        assert any(line.startswith(f"imssr: seed {seed}: agent step 80/80 (100.0%)") for line in progress), progress
    assert len(evaluations) == 2 and len(progress) == 2 * 80


def test_runs_of_one_seed_are_told_apart_by_their_algorithm():
    from imssr.training.progress import member_labels

    assert member_labels([1, 2], ["curl", "curl"], ["a", "b"]) == ["seed 1", "seed 2"]
    assert member_labels([1, 1], ["curl", "im-curl"], ["a", "b"]) == ["curl seed 1", "im-curl seed 1"]
    assert member_labels([1, 1], ["im-curl", "im-curl"], ["x/beta0_0.01", "x/beta0_0.1"]) == \
        ["x/beta0_0.01", "x/beta0_0.1"]


def test_two_evaluation_scenes_in_lockstep_are_each_seeds_own(tmp_path, alone):
    """With two evaluation scenes, each seed's eval.csv is its run alone's."""
    cfgs = configs(steps=80)
    for cfg in cfgs:
        cfg.train.eval_modes = "training,color_easy"
        cfg.train.eval_every_steps = 80
    assert train_seeds(tmp_path / "batch", cfgs=cfgs) == [None, None]
    batched = rows(os.path.join(runs(tmp_path / "batch")[1], "eval.csv"))
    assert [r["mode"] for r in batched] == ["training", "color_easy"]
    assert batched == rows(os.path.join(alone(cfgs[1]), "eval.csv"))


def test_the_resume_command_names_seeds_or_run_directories(tmp_path):
    trainer = SeedsTrainer(configs(), runs(tmp_path))
    try:
        assert trainer.resume_command() == f"imssr train --seeds 1,2 --out {tmp_path} --resume"
    finally:
        trainer.close()
    dirs = [str(tmp_path / "x" / name) for name in ("curl", "im-curl")]
    trainer = SeedsTrainer(configs(), dirs)
    try:
        assert trainer.resume_command() == f"imssr train --runs {' '.join(dirs)} --resume"
    finally:
        trainer.close()


def imssr(*args):
    return run_imssr(*args, check=False, env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})


@pytest.mark.parametrize("args, message", [
    (["--seeds", "1-2"], "--seeds needs --out DIR"),
    (["--seeds", "1-2", "--seed", "3", "--out", "X"], "--seeds and --seed exclude each other"),
    (["--seeds", "2-1", "--out", "X"], "bad seed range"),
    (["--seeds", "-1", "--out", "X"], "seeds must be an integer in [0, 2147483647] (numpy and dm_control take "
                                      "32-bit seeds, and evaluation adds up to 20000), got -1"),
    (["--seeds", "0--2", "--out", "X"], "seeds must be an integer in [0, 2147483647]"),
    (["--seeds", "1,1", "--out", "X"], "seed 1 is named twice in --seeds 1,1: each seed trains one run; name it once"),
    (["--seeds", "1-3,2", "--out", "X"], "seed 2 is named twice"),
    (["--seeds", "1,,2", "--out", "X"], "bad seeds '1,,2': an empty item between commas"),
    (["--seeds", "1,2,", "--out", "X"], "bad seeds '1,2,': an empty item between commas"),
])
def test_seeds_errors_are_one_line(args, message, tmp_path, capsys):
    assert cli_status("train", "--algo", "curl", "--task", "cartpole_swingup",
                      *[a.replace("X", str(tmp_path / "x")) for a in args]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("second, message", [
    ("D", "imssr: error: D is named twice: each run trains once, so name it once"),
    ("ABS", "imssr: error: D and ABS are one directory: each run trains once, so name it once"),
    ("LINK", "imssr: error: D and LINK are one directory: each run trains once, so name it once"),
])
def test_runs_naming_one_directory_twice_are_refused(second, message, tmp_path):
    """``--runs D D``, ``--runs D /abs/D`` and a link to D: one directory, refused before it is locked
    (the second lock would be the process's own: "in use by PID" of itself)."""
    os.makedirs(tmp_path / "D")
    RunDir(str(tmp_path / "D")).write_config(tiny_config("curl"))
    os.symlink(tmp_path / "D", tmp_path / "LINK")
    second = {"D": "D", "ABS": str(tmp_path / "D"), "LINK": "LINK"}[second]
    before = sorted(os.listdir(tmp_path / "D"))
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
           "PYTHONPATH": os.pathsep.join([REPO, os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-m", "imssr", "train", "--runs", "D", second], capture_output=True,
                          text=True, cwd=tmp_path, env=env, timeout=300)
    assert proc.returncode == 2
    assert proc.stderr.strip() == message.replace("ABS", str(tmp_path / "D"))
    assert sorted(os.listdir(tmp_path / "D")) == before


def test_cli_trains_seeds_into_their_directories(tmp_path):
    out = tmp_path / "batch"
    proc = imssr("train", "--algo", "curl", "--task", "cartpole_swingup_sparse", "--seeds", "3,5",
                 "--out", str(out), "--steps", "70", "--seed-steps", "60", "--eval-every", "70",
                 "--eval-episodes", "1", "--no-progress", "--no-tensorboard", *tiny_sets(),
                 "--set", "train.burst_updates=0", "--set", "train.replay_capacity=1000")
    assert proc.returncode == 0, proc.stderr
    assert "seeds 3,5 in one process" in proc.stdout
    for seed in (3, 5):
        run = out / f"seed_{seed}"
        assert json.load(open(run / "config.json"))["train"]["seed"] == seed
        assert (run / "learning_curve.png").exists()
        assert RunDir(str(run)).checkpoint().checkpoint.step == 70


def test_runs_of_curl_and_im_curl_train_in_one_process(tmp_path):
    """``imssr train --runs`` trains run directories described by their config.json (as a sweep
    writes them): the base and its IM- variant in one batch."""
    dirs = []
    for algo in ("curl", "im-curl"):
        cfg = tiny_config(algo, seed=4, steps=70, seed_steps=60, eval_every_steps=70)
        run = RunDir(str(tmp_path / algo))
        os.makedirs(run.path)
        run.write_config(cfg)
        dirs.append(run.path)
    proc = imssr("train", "--runs", *dirs, "--no-progress")
    assert proc.returncode == 0, proc.stderr
    assert "curl, im-curl on cartpole_swingup_sparse, seeds 4,4 in one process" in proc.stdout
    for run in dirs:
        assert RunDir(run).checkpoint().checkpoint.step == 70
    assert [RunDir(run).read_config().intrinsic.enabled for run in dirs] == [False, True]


def test_runs_that_differ_elsewhere_are_refused_in_one_line(tmp_path):
    cfgs = [tiny_config("curl", seed=1), tiny_config("curl", seed=2, steps=300)]
    with pytest.raises(Exception, match=r"^runs in one process must share every setting but the seed and the "
                                        r"intrinsic reward: train.steps is 250 in one and 300 in another$"):
        SeedsTrainer(cfgs, [str(tmp_path / "a"), str(tmp_path / "b")])


def test_what_may_share_a_process_is_decided_from_the_configs():
    """Runs share a process when they differ in the seed and the intrinsic reward's beta_0 and
    switch only: members with and without a signal of weights of its own (RND) too."""
    from imssr.config.batching import batch_key, batch_refusal

    curl, rnd, im = tiny_config("curl", seed=1), tiny_config("curl+rnd", seed=2), tiny_config("im-curl", seed=3)
    assert batch_refusal([curl, rnd]) is None and batch_refusal([curl, im]) is None
    assert batch_key(curl)[0] == batch_key(rnd)[0] == batch_key(im)[0]
    assert batch_key(curl)[1] is None and batch_key(rnd)[1] != batch_key(im)[1]
    assert batch_refusal([rnd, im]) == "the runs of one process may differ in intrinsic.beta0 and intrinsic.enabled only"
    other = tiny_config("im-curl", seed=4)
    other.intrinsic.beta0 = 0.5
    assert batch_refusal([im, other]) is None and batch_key(im) == batch_key(other)
    im.agent.compile = "default"
    assert batch_refusal([im, other]).endswith("set agent.compile=off")


def test_envs_in_worker_processes_change_nothing(uninterrupted, tmp_path):
    """train.env_workers: every env in a process of its own, stepped ahead while the agent
    learns; the seeds' logs and weights are those of the envs in the training's process."""
    cfgs = configs()
    for cfg in cfgs:
        cfg.train.env_workers = True
    assert train_seeds(tmp_path, cfgs=cfgs) == [None, None]
    assert_same_as_uninterrupted(uninterrupted, tmp_path)


# -- a batch's checkpoint is every run's or none; a refused batch writes nothing ---------------------

def files_of(root) -> dict[str, bytes]:
    """Every file under ``root`` but the runs' lock files (a killed process's is taken over and
    released), by its path relative to it, with its bytes."""
    from imssr.rundir import LOCK_FILE

    out = {}
    for folder, _, names in os.walk(root):
        for name in names:
            if name == LOCK_FILE:
                continue
            path = os.path.join(folder, name)
            with open(path, "rb") as fh:
                out[os.path.relpath(path, root)] = fh.read()
    return out


def assert_same_as_uninterrupted(done_root, root) -> None:
    for done, other in zip(runs(done_root), runs(root)):
        assert_same_run(other, done)


KILLED_AT = """
import os, signal, sys

import imssr.rundir.checkpoint as checkpoint

write, copy = checkpoint.write_checkpoint, checkpoint.copy_checkpoint
times = [int(os.environ["KILL_TIME"])]


def kill_at(path):
    if path == os.environ["KILL_AT"]:
        times[0] -= 1
        if not times[0]:
            os.kill(os.getpid(), signal.SIGKILL)  # as SIGKILL from outside, as this file is written


checkpoint.write_checkpoint = lambda path, ckpt: kill_at(path) or write(path, ckpt)
checkpoint.copy_checkpoint = lambda src, dst: kill_at(dst) or copy(src, dst)
from imssr.cli import main

sys.exit(main(sys.argv[1:]))
"""


def killed_batch(root, kill_at: str, time: int = 1, cfgs=None) -> None:
    """``imssr train --runs`` of the seeds' runs in ``root`` (of ``cfgs``, with the torch threads of
    this process), SIGKILLed as ``kill_at`` is written for the ``time``-th time."""
    cfgs = cfgs or configs()
    for cfg, run in zip(cfgs, runs(root, len(cfgs))):
        RunDir(run).write_config(cfg)
    proc = subprocess.run([sys.executable, "-c", KILLED_AT, "train", "--runs", *runs(root, len(cfgs))],
                          capture_output=True, text=True, timeout=900,
                          env={**os.environ, "KILL_AT": kill_at, "KILL_TIME": str(time),
                               "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    assert proc.returncode == -9, proc.stdout + proc.stderr


def test_a_batch_killed_between_its_runs_first_saves_resumes_as_a_fresh_start(uninterrupted, tmp_path, capsys):
    """Killed after seed 1 saved its first checkpoint and before seed 2 did: ``--resume`` says in one
    line to start afresh (and writes nothing), and a sweep's retry of the packed runs (``imssr
    train --runs``, fresh: not every run has a checkpoint) clears what the kill left and trains the
    runs as the uninterrupted batch did."""
    from imssr.cli import main
    from imssr.sweep.runner import execute_runs

    killed_batch(tmp_path, os.path.join(runs(tmp_path)[1], "checkpoints", "step-000000125.pt"))
    first = RunDir(runs(tmp_path)[0])
    assert first.checkpoint_steps() == [125] and not RunDir(runs(tmp_path)[1]).has_checkpoint()

    before = files_of(tmp_path)
    assert main(["train", "--seeds", "1,2", "--out", str(tmp_path), "--resume"]) == 2
    out, err = capsys.readouterr()
    assert err == (f"imssr: error: nothing to resume as one batch: {runs(tmp_path)[1]} holds no checkpoint (the "
                   "batch stopped during its first one); start every run afresh: the same command without "
                   "--resume\n")
    assert "resuming from" not in out and files_of(tmp_path) == before

    results = execute_runs(runs(tmp_path), 150, attempt=2)
    assert [r["ok"] for r in results] == [True, True], results
    assert [r["resumed"] for r in results] == [False, False]
    assert "clearing what a batch stopped before its first checkpoint was complete left" in \
        open(os.path.join(runs(tmp_path)[0], "sweep.log")).read()
    assert_same_as_uninterrupted(uninterrupted, tmp_path)


def test_a_batch_whose_second_run_fails_to_save_resumes_from_the_last_complete_checkpoint(
        uninterrupted, tmp_path, monkeypatch, capsys):
    """Seed 2's checkpoint of step 150 fails (an I/O error) after seed 1 saved its own: seed 1's is
    removed, every run keeps the checkpoint of step 125, and the resume from it ends as the
    uninterrupted batch."""
    from imssr.rundir import checkpoint

    write = checkpoint.write_checkpoint
    second = os.path.join(runs(tmp_path)[1], "checkpoints", "step-000000150.pt")

    def failing(path, ckpt):
        if path == second:
            raise OSError(errno.EIO, "Input/output error", path)
        return write(path, ckpt)

    monkeypatch.setattr(checkpoint, "write_checkpoint", failing)
    with pytest.raises(OSError, match="Input/output error"):
        train_seeds(tmp_path)
    monkeypatch.undo()
    for run in runs(tmp_path):
        assert RunDir(run).checkpoint().checkpoint.step == 125 and RunDir(run).checkpoint_steps() == [125]
        assert json.load(open(os.path.join(run, "status.json")))["state"] == "failed"
    assert train_seeds(tmp_path, resume=True) == [None, None]
    assert_same_as_uninterrupted(uninterrupted, tmp_path)


def test_a_refused_batch_resume_writes_nothing(uninterrupted, tmp_path, capsys):
    """Another process holds seed 2 (here: this test): the resume of the batch, with a new budget,
    is refused before any run's config.json, provenance, logs or status changes, and says nothing
    of resuming."""
    import shutil

    from imssr.rundir.lock import DirectoryLock

    shutil.copytree(uninterrupted, tmp_path, dirs_exist_ok=True)
    before = files_of(tmp_path)
    lock = DirectoryLock(runs(tmp_path)[1]).acquire()
    try:
        with pytest.raises(ImssrError, match=f"^{runs(tmp_path)[1]} is in use by PID {os.getpid()}"):
            train_seeds(tmp_path, resume=True, cfgs=configs(steps=200))
    finally:
        lock.release()
    assert files_of(tmp_path) == before
    assert "resuming from" not in capsys.readouterr().out


def test_a_batch_that_finds_a_run_taken_leaves_no_trace(tmp_path):
    """A fresh batch whose second run another process holds: the first run's directory is not even
    made (no config.json, no "start" record that a report would count)."""
    from imssr.rundir.lock import DirectoryLock

    lock = DirectoryLock(runs(tmp_path)[1]).acquire()
    try:
        with pytest.raises(ImssrError, match="is in use by PID"):
            train_seeds(tmp_path)
    finally:
        lock.release()
    assert sorted(os.listdir(tmp_path)) == []


# -- what a refused batch resume advises works when followed ---------------------------------

ALONE = ["--algo", "curl", "--task", "cartpole_swingup_sparse", "--seed-steps", "60", "--eval-every", "40",
         "--eval-episodes", "1", "--checkpoint-every", "40", "--no-progress", "--no-tensorboard", *tiny_sets(),
         "--set", "train.burst_updates=0", "--set", "train.replay_capacity=1000",
         "--set", f"train.torch_threads={TORCH_THREADS}"]


def test_the_advice_for_runs_at_different_steps_works_as_given(tmp_path, capsys):
    """Seed 1 trained alone to agent step 80 and seed 2 to 120 share no checkpoint. Resumed
    together with a budget of 100, which seed 2 is already past, the line names the two commands
    to run; run as given, they succeed, and both runs end at one step."""
    first, second = str(tmp_path / "seed_1"), str(tmp_path / "seed_2")
    assert cli_status("train", *ALONE, "--seed", "1", "--steps", "80", "--out", first) == 0
    assert cli_status("train", *ALONE, "--seed", "2", "--steps", "120", "--out", second) == 0
    capsys.readouterr()
    assert cli_status("train", "--runs", first, second, "--resume", "--steps", "100", "--no-progress") == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and f"bring {first} to step 120 alone first" in err, err
    alone, together = re.search(r"\((imssr train --out RUN_DIR --resume --steps \d+)\), then resume them together "
                                r"with (--steps \d+)", err).groups()
    assert cli_status(*alone.replace("RUN_DIR", first).split()[1:], "--no-progress") == 0
    assert cli_status("train", "--runs", first, second, "--resume", *together.split(), "--no-progress") == 0, \
        capsys.readouterr().err
    assert [RunDir(run).checkpoint().checkpoint.step for run in (first, second)] == [120, 120]


KILLED_IN_WRITE = """
import os, signal, sys

import imssr.rundir.checkpoint as checkpoint
from imssr.files import temp_file_target

sealed = checkpoint._write_sealed


def killing(state, path):
    # ``path`` is atomic_path's temporary file beside the checkpoint it becomes.
    if os.path.join(os.path.dirname(path), temp_file_target(os.path.basename(path)) or "") == os.environ["KILL_AT"]:
        os.kill(os.getpid(), signal.SIGKILL)  # as SIGKILL from outside, the temporary file made
    sealed(state, path)


checkpoint._write_sealed = killing
from imssr.cli import main

sys.exit(main(sys.argv[1:]))
"""


def test_a_batch_killed_in_its_first_runs_first_write_is_told_to_start_afresh(tmp_path, capsys):
    """Killed as seed 1 writes its first checkpoint (a temporary file, no checkpoint in any run):
    ``--resume`` says in one line to start every run afresh, and the same command without it
    does."""
    for cfg, run in zip(configs(), runs(tmp_path)):
        RunDir(run).write_config(cfg)
    proc = subprocess.run([sys.executable, "-c", KILLED_IN_WRITE, "train", "--runs", *runs(tmp_path)],
                          capture_output=True, text=True, timeout=900,
                          env={**os.environ, "KILL_AT": os.path.join(runs(tmp_path)[0], "checkpoints",
                                                                     "step-000000125.pt"),
                               "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    assert proc.returncode == -9, proc.stdout + proc.stderr
    assert any(name.startswith(".tmp-") for name in os.listdir(os.path.join(runs(tmp_path)[0], "checkpoints")))
    assert not any(RunDir(run).has_checkpoint() for run in runs(tmp_path))

    before = files_of(tmp_path)
    assert cli_status("train", "--runs", *runs(tmp_path), "--resume", "--no-progress") == 2
    assert capsys.readouterr().err == (
        "imssr: error: nothing to resume: no run of the batch holds a checkpoint (the batch stopped before its "
        "first checkpoint was complete); start every run afresh: the same command without --resume\n")
    assert files_of(tmp_path) == before
    assert cli_status("train", "--runs", *runs(tmp_path), "--no-progress") == 0
    assert [RunDir(run).checkpoint().checkpoint.step for run in runs(tmp_path)] == [150, 150]


def test_sigterm_while_the_batch_is_built_stops_it_there(tmp_path):
    """SIGTERM as the members of a batch are built (a minute for dozens of them) ends the batch
    at the next member with exit status 130 and one line, before any run is written."""
    import signal
    import time

    out = tmp_path / "b"
    cmd = [sys.executable, "-m", "imssr", "train", "--algo", "curl", "--task", "cartpole_swingup", "--steps", "250",
           "--seeds", "1-30", "--no-progress", "--no-tensorboard", *tiny_sets(), "--set", "train.replay_capacity=3000",
           "--out", str(out)]
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 120
        # Every seed's directory is locked before the first member is built.
        while not (out / "seed_30").exists():
            assert proc.poll() is None and time.time() < deadline, proc.communicate()
            time.sleep(0.05)
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        sent = time.time()
        stdout, stderr = proc.communicate(timeout=60)
        took = time.time() - sent
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, stdout + stderr
    lines = [line for line in stderr.splitlines() if "as the batch started" in line]
    assert len(lines) == 1 and re.search(r"stopped by SIGTERM as the batch started \(\d+ of 30 runs built\)",
                                         lines[0]), stderr
    assert took < 15, took
    assert not any((out / f"seed_{s}" / "train.csv").exists() for s in range(1, 31))
    assert not any((out / f"seed_{s}" / "config.json").exists() for s in range(1, 31))
