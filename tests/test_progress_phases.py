"""Progress inside the long phases between two agent steps (the burst of updates, evaluations,
checkpoints, a resume's loading, ``imssr evaluate``'s episodes): lines in a log while the phase
lasts, none after it, and none at all with ``train.progress=false``."""
from __future__ import annotations

import io
import re
import sys
import threading
import time

import pytest

import imssr
from conftest import TINY, assert_same_tensors, tiny_config, tiny_overrides, without_timing
from imssr.cli import build_parser
from imssr.files import read_csv
from imssr.rundir import RunDir
from imssr.rundir.checkpoint import load_checkpoint
from imssr.training import Trainer, progress
from imssr.training.checkpointing import Checkpointer
from imssr.training.evaluate import evaluate_run
from imssr.training.progress import phase
from imssr.training.seeds import SeedsTrainer
from imssr.training.stop import TrainingInterrupted

TASK = "cartpole_swingup_sparse"

EVERY_S = 0.01
"""Seconds between a phase's lines here: every phase of a tiny run outlasts it but a checkpoint's
write, which :func:`seen_before_it_ends` holds open until its first line."""

LINE = re.compile(r"imssr: (?:seed \d+: )?(?P<what>.+?)(?:, (?P<done>[\d,]+)/(?P<total>[\d,]+) (?P<unit>\w+) done)?, "
                  r"\d+:\d\d:\d\d so far")


def burst_config(**train):
    """A tiny run whose seed phase ends at agent step 60 with a burst of 30 updates; evaluated
    and checkpointed where its budget of 70 agent steps runs out."""
    return tiny_config("curl", TASK, **{"steps": 70, "seed_steps": 60, "burst_updates": 30, "eval_every_steps": 0,
                                        "checkpoint_every_steps": 0, "progress": True, **train})


class Stdout(io.StringIO):
    """stdout that is no terminal (a log), written to by the training and the phases' threads."""

    def __init__(self):
        super().__init__()
        self.lock = threading.Lock()

    def write(self, text: str) -> int:
        with self.lock:
            return super().write(text)

    def text(self) -> str:
        with self.lock:
            return self.getvalue()

    def phase_lines(self) -> list[re.Match]:
        return [m for m in map(LINE.fullmatch, self.text().splitlines()) if m]


def seen_before_it_ends(monkeypatch, out: Stdout, cls, name: str, what: str) -> None:
    """``cls.name`` (a checkpoint's write or load, which may end within :data:`EVERY_S` on a fast
    disk) returns once ``out`` holds a line of the phase ``what``: the phase lasts until its
    thread has spoken, whatever the machine's speed."""
    real = getattr(cls, name)

    def held(*args, **kw):
        result = real(*args, **kw)
        deadline = time.monotonic() + 120
        while not any(m["what"].endswith(what) for m in out.phase_lines()):
            assert time.monotonic() < deadline, f"no line of {what!r}: {out.text()}"
            time.sleep(0.005)
        return result
    monkeypatch.setattr(cls, name, held)


def progress_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "imssr-progress"]


def as_log(monkeypatch) -> Stdout:
    """sys.stdout as a log file (no terminal), where a run's progress lines go, a line of a phase
    every :data:`EVERY_S` seconds.  In a test, set in its body: pytest sets its own sys.stdout
    again after a fixture's setup."""
    out = Stdout()
    monkeypatch.setattr(sys, "stdout", out)
    monkeypatch.setattr(Trainer, "progress_every_s", EVERY_S)
    return out


@pytest.fixture(scope="module")
def burst_run(tmp_path_factory) -> tuple[str, Stdout]:
    """A run of :func:`burst_config` trained with progress on and its stdout a log: the run
    directory and what it printed."""
    run = str(tmp_path_factory.mktemp("progress") / "run")
    with pytest.MonkeyPatch.context() as mp:
        out = as_log(mp)
        seen_before_it_ends(mp, out, Checkpointer, "save", "writing the checkpoint")
        t = Trainer(burst_config(), run)
        try:
            t.train()
        finally:
            t.close()
    return run, out


def test_the_burst_the_evaluation_and_the_checkpoint_say_how_far_they_are(burst_run):
    run, out = burst_run
    lines = out.phase_lines()
    burst = [m for m in lines if m["what"] == "agent step 60: burst of updates"]
    assert burst and all((m["total"], m["unit"]) == ("30", "updates") for m in burst), out.text()
    counts = [int(m["done"]) for m in burst]
    assert counts == sorted(counts) and counts[-1] <= 30
    evaluation = [m for m in lines if m["what"] == "agent step 70: evaluation"]
    assert evaluation and all((m["total"], m["unit"]) == ("1", "episodes") for m in evaluation), out.text()
    assert any(m["what"] == "agent step 70: writing the checkpoint" and m["total"] is None for m in lines)
    assert "frames/s" in out.text()  # the agent steps' lines go on around the phases
    assert not progress_threads()


def test_a_resume_says_how_far_its_loading_is_and_imssr_evaluate_its_episodes(burst_run, monkeypatch):
    run, _ = burst_run
    out = as_log(monkeypatch)
    seen_before_it_ends(monkeypatch, out, Checkpointer, "restore", "loading the checkpoint")
    # The checkpoint's replay buffer: gigabytes at the paper's size.
    Trainer(burst_config(steps=80), run, resume=True).close()
    assert [m["what"] for m in out.phase_lines()][:1] == ["resuming from agent step 70: loading the checkpoint"], \
        out.text()

    # `imssr evaluate`: each scene's episodes, as they are played; --no-progress: no lines.
    monkeypatch.setattr(progress, "PROGRESS_EVERY_S", EVERY_S)
    said = len(out.phase_lines())
    evaluate_run(run, episodes=1, progress=False)
    assert len(out.phase_lines()) == said
    evaluate_run(run, episodes=1, modes="training,color_easy")
    scenes = {(m["what"], m["total"], m["unit"]) for m in out.phase_lines()[said:]}
    assert scenes == {("evaluating in training", "1", "episodes"), ("evaluating in color_easy", "1", "episodes")}, \
        out.text()
    assert not progress_threads()
    assert build_parser().parse_args(["evaluate", "--run", run, "--no-progress"]).no_progress


def test_progress_off_shows_nothing_and_trains_the_same_numbers(burst_run, tmp_path, capfd, monkeypatch):
    """``imssr.train(progress=False)``: no bar, no progress line, in the phases either; the run
    is bit-identical to the one with progress on (the phases' threads touch no generator)."""
    shown, _ = burst_run
    monkeypatch.setattr(Trainer, "progress_every_s", EVERY_S)
    off = str(tmp_path / "run")
    settings = {**TINY, "train.replay_capacity": 5000, "train.seed_steps": 60, "train.burst_updates": 30,
                "train.eval_every_steps": 0, "train.eval_episodes": 1, "train.checkpoint_every_steps": 0,
                "train.tensorboard": False}
    imssr.train("curl", TASK, out=off, steps=70, progress=False, overrides=tiny_overrides(settings))
    out, err = capfd.readouterr()
    assert "imssr: done; " in out  # what the run says, progress or not
    assert not [line for line in (out + err).splitlines() if "so far" in line or "frames/s" in line], out + err
    assert "\r" not in err and "it/s" not in err and "updates/s" not in err  # no bar

    assert RunDir(off).read_config() == burst_config(progress=False)
    on_ckpt, off_ckpt = (load_checkpoint(RunDir(r).latest) for r in (shown, off))
    assert (on_ckpt.step, off_ckpt.step) == (70, 70)
    assert assert_same_tensors(on_ckpt.agent, off_ckpt.agent) > 0
    assert without_timing(read_csv(RunDir(shown).log("train"))) == without_timing(read_csv(RunDir(off).log("train")))


def test_a_stop_inside_the_burst_ends_its_lines_with_it(tmp_path, monkeypatch):
    """SIGTERM during the burst: the checkpoint of the updates done and TrainingInterrupted leave
    the burst's phase; its thread has stopped, so nothing more is said."""

    log_stdout = as_log(monkeypatch)

    class StopInBurst:
        """A stop request that arrives once the agent has made 15 updates and the burst said so."""

        @property
        def signal_name(self):
            burst = [m for m in log_stdout.phase_lines() if m["what"] == "agent step 60: burst of updates"]
            return "SIGTERM" if t.agent.updates >= 15 and burst else None

    t = Trainer(burst_config(), str(tmp_path / "run"))
    try:
        t.stop = StopInBurst()
        with pytest.raises(TrainingInterrupted, match="^stopped at agent step 60 by SIGTERM;"):
            t.train()
    finally:
        t.close()
    assert not progress_threads()
    said = log_stdout.text()
    time.sleep(10 * EVERY_S)
    assert log_stdout.text() == said


def test_a_phase_that_raises_stops_its_thread_and_says_nothing_after(monkeypatch):
    log_stdout = as_log(monkeypatch)
    with pytest.raises(KeyboardInterrupt):
        with phase("agent step 5: burst of updates", 10, "updates", every_s=EVERY_S) as shown:
            shown.advance(3)
            while not log_stdout.phase_lines():
                time.sleep(0.005)
            raise KeyboardInterrupt
    assert not progress_threads()
    said = log_stdout.text()
    assert LINE.fullmatch(said.splitlines()[0])["done"] == "3"
    assert said.splitlines()[0].startswith("imssr: agent step 5: burst of updates, 3/10 updates done, 0:00:00")
    time.sleep(10 * EVERY_S)
    assert log_stdout.text() == said


def test_a_batch_says_its_burst_once_and_each_seeds_evaluation_and_checkpoint(tmp_path, monkeypatch):
    log_stdout = as_log(monkeypatch)
    seen_before_it_ends(monkeypatch, log_stdout, Checkpointer, "save", "writing the checkpoint")
    cfgs = [burst_config(seed=seed) for seed in (1, 2)]
    trainer = SeedsTrainer(cfgs, [str(tmp_path / f"seed_{c.train.seed}") for c in cfgs])
    try:
        assert trainer.train() == [None, None]
    finally:
        trainer.close()
    text = log_stdout.text()
    lines = text.splitlines()
    assert any(line.startswith("imssr: agent step 60: burst of updates of 2 seeds, ") for line in lines), text
    # The first seed plays every seed's evaluation episodes in lockstep.
    assert any(line.startswith("imssr: seed 1: agent step 70: evaluation, ") for line in lines), text
    for seed in (1, 2):
        assert any(line.startswith(f"imssr: seed {seed}: agent step 70: writing the checkpoint, ")
                   for line in lines), text
    assert not progress_threads()
