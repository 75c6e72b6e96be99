"""Checkpoints: round trip, exact resume after a kill, corrupt and mismatched files."""
import copy
import os
import zipfile

import numpy as np
import pytest
import torch

from conftest import a_checkpoint, assert_same_tensors, tiny_config, train_run, train_stopped_at, without_timing
from imssr.errors import ImssrError
from imssr.integrity import seal_zip
from imssr.training import Trainer
from imssr.training.loop import TrainingInterrupted
from imssr.rundir import RunDir
from imssr.rundir.checkpoint import CheckpointDamaged, load_checkpoint
from imssr.training.logger import read_csv
from imssr.training.state import StepSchedule


def _cfg():
    # 2 episodes of cartpole (125 agent steps each), checkpoints after each.
    return tiny_config("im-curl", steps=250, seed_steps=60, eval_every_steps=125,
                       checkpoint_every_steps=125)


def _train(out, stop_at=None, resume=False, **kw):
    return train_run(_cfg(), out, stop_at, resume, **kw)


_strip = without_timing


@pytest.fixture(scope="module")
def full_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("full")
    return out, _train(out)


def test_resume_after_kill_reaches_the_same_final_state(full_run, tmp_path):
    full_dir, full = full_run
    # Stop at the episode end with the checkpoint at frame 1000, then resume in a new Trainer.
    part = _train(tmp_path, stop_at=125)
    assert part.frame == 1000
    resumed = _train(tmp_path, resume=True)
    assert resumed.frame == full.frame == 2000 and resumed.step == full.step
    a, b = full.agent.state_dict(), resumed.agent.state_dict()
    for k, v in a["nets"].items():
        assert torch.equal(v, b["nets"][k]), k
    assert torch.equal(a["aux"]["module"]["W"], b["aux"]["module"]["W"])
    for name in ("train.csv", "eval.csv", "eval_episodes.csv"):
        assert _strip(read_csv(full_dir / name)) == _strip(read_csv(tmp_path / name)), name


def test_checkpoints_change_no_number_of_a_run(full_run, tmp_path):
    """A run with no checkpoint before its end and none of its replay frames saved (what
    scripts/lease_results.py trains with) equals the run that checkpointed with its frames after
    each episode: agent, generators, counters and logs."""
    cfg = _cfg()
    cfg.train.checkpoint_every_steps, cfg.train.save_buffer = 0, False
    train_run(cfg, tmp_path)
    assert load_checkpoint(RunDir(str(tmp_path)).latest).replay_file is None
    _assert_same_runs(full_run[0], tmp_path)


def _short(steps, **train):
    # Episodes of 125 agent steps; learning from agent step 60, an evaluation every 125.
    return tiny_config("im-curl", steps=steps, seed_steps=60, eval_every_steps=125,
                       checkpoint_every_steps=0, **train)


def _assert_same_runs(a_dir, b_dir):
    """Two runs' final checkpoints hold the same tensors (agent, optimisers, generators, replay
    state) and counters, and their logs the same rows."""
    a, b = (load_checkpoint(RunDir(str(d)).latest).to_state() for d in (a_dir, b_dir))
    for key in ("agent", "replay_state", "global_rng", "env_rng", "eval_env_rngs", "action_rng", "step", "frame",
                "episode", "eval_history"):
        if key == "eval_history":
            a[key], b[key] = ([dict(item, row=_strip([item["row"]])[0]) for item in x[key]] for x in (a, b))
        assert_same_tensors(a[key], b[key], key)
    for name in ("train.csv", "eval.csv", "eval_episodes.csv"):
        assert _strip(read_csv(a_dir / name)) == _strip(read_csv(b_dir / name)), name


def test_extending_a_run_whose_budget_ended_mid_episode_is_exact(tmp_path):
    """`--steps 140`, then `--resume --steps 160`, equals `--steps 160`: the final checkpoint
    holds the open episode, and the final evaluation at agent step 140 (off the schedule) is
    one that a run with the larger budget never made."""
    direct, extended = tmp_path / "direct", tmp_path / "extended"
    train_run(_short(160), direct)
    train_run(_short(140), extended)
    assert [r["step"] for r in read_csv(extended / "eval.csv")] == ["125", "140"]
    state = load_checkpoint(RunDir(str(extended)).latest)
    assert state.step == 140 and state.episode_state is not None
    again = train_run(_short(140), extended, resume=True)  # the same budget: nothing to do
    assert again.step == 140 and load_checkpoint(RunDir(str(extended)).latest).step == 140
    train_run(_short(160), extended, resume=True)
    _assert_same_runs(direct, extended)


def test_a_run_stopped_mid_episode_and_resumed_to_that_step_checkpoints_its_final_evaluation(tmp_path):
    """Stopped at agent step 140 (mid-episode, checkpointed), resumed with `--steps 140`: the
    final evaluation runs, and the checkpoint holds it as a `--steps 140` run's does."""
    direct, stopped = tmp_path / "direct", tmp_path / "stopped"
    train_run(_short(140), direct)
    train_run(_short(160), stopped, stop_at=140)
    assert [r["step"] for r in read_csv(stopped / "eval.csv")] == ["125"]
    train_run(_short(140), stopped, resume=True)
    state = load_checkpoint(RunDir(str(stopped)).latest)
    assert [item["row"]["step"] for item in state.eval_history] == [125, 140]
    assert state.before_final_eval is not None
    _assert_same_runs(direct, stopped)


def test_a_stop_inside_the_burst_of_updates_resumes_exactly(tmp_path):
    """A stop request during the seed phase's burst checkpoints the burst where it is; the
    resume does the rest of it, takes the action drawn before it, and ends as a run never stopped."""

    class StopInBurst:
        """A stop request that arrives once the agent has made ``updates`` updates."""

        def __init__(self, trainer, updates):
            self.trainer, self.updates = trainer, updates

        @property
        def signal_name(self):
            return "SIGTERM" if self.trainer.agent.updates >= self.updates else None

    direct, stopped = tmp_path / "direct", tmp_path / "stopped"
    train_run(_short(130, burst_updates=40), direct)
    t = Trainer(_short(130, burst_updates=40), str(stopped))
    try:
        t.stop = StopInBurst(t, 15)
        with pytest.raises(TrainingInterrupted, match="^stopped at agent step 60 by SIGTERM;"):
            t.train()
    finally:
        t.close()
    state = load_checkpoint(RunDir(str(stopped)).latest)
    assert state.step == 60 and state.agent["updates"] == 15
    assert state.burst_state["updates_done"] == 15 and state.episode_state is not None
    train_run(_short(130, burst_updates=40), stopped, resume=True)
    _assert_same_runs(direct, stopped)


def test_checkpoint_contents_and_round_trip(full_run):
    full_dir, full = full_run
    state = load_checkpoint(RunDir(str(full_dir)).latest)
    assert state.frame == 2000 and state.step == 250 and state.episode == 2
    assert os.path.exists(full_dir / "checkpoints" / state.replay_file)
    t = Trainer(_cfg(), str(full_dir), resume=True)  # loads everything, nothing left to do
    try:
        obs, _ = next(iter(t.eval_envs.values())).reset()
        assert np.array_equal(t.agent.act(obs, True), full.agent.act(obs, True))
        assert t.replay.size == full.replay.size
        assert np.array_equal(t.replay.frames[: t.replay.size], full.replay.frames[: full.replay.size])
    finally:
        t.close()


def test_fresh_run_refuses_to_overwrite(full_run):
    full_dir, _ = full_run
    with pytest.raises(ImssrError, match="already holds a run"):
        Trainer(_cfg(), str(full_dir))


def test_corrupt_checkpoint_gives_clear_error(tmp_path):
    path = tmp_path / "checkpoints" / "latest.pt"
    path.parent.mkdir()
    path.write_bytes(b"\x00garbage")
    with pytest.raises(ImssrError, match=r"not an imssr checkpoint \(not a torch checkpoint file\)"):
        load_checkpoint(str(path))
    with pytest.raises(ImssrError, match="not an imssr checkpoint"):
        Trainer(_cfg(), str(tmp_path), resume=True)
    torch.save({"something": 1}, str(path))
    seal_zip(str(path))  # sealed, as if imssr wrote it: what is inside is checked on its own
    whole = path.read_bytes()
    with pytest.raises(ImssrError, match="not an imssr checkpoint of format"):
        load_checkpoint(str(path))
    path.write_bytes(whole[:len(whole) // 2])
    with pytest.raises(CheckpointDamaged, match=r"^corrupt checkpoint .*: cut short"):
        load_checkpoint(str(path))
    with zipfile.ZipFile(path, "w") as archive:  # a zip archive whose pickle is text
        archive.writestr("archive/data.pkl", b"hello world")
        archive.writestr("archive/version", "3\n")
    seal_zip(str(path))
    with pytest.raises(CheckpointDamaged, match=r"^corrupt checkpoint .*: KeyError: 101$"):
        load_checkpoint(str(path))


def test_a_failure_that_is_not_the_files_is_not_called_a_damaged_checkpoint(tmp_path, monkeypatch):
    """Out of memory (or a bug) while loading must not read as a damaged file, which a resume
    would quietly skip for an older checkpoint."""
    run = RunDir(str(tmp_path))
    run.save_checkpoint(a_checkpoint(step=5), keep=1)

    def out_of_memory(*args, **kwargs):
        raise MemoryError()

    monkeypatch.setattr(torch, "load", out_of_memory)
    with pytest.raises(MemoryError):
        run.checkpoint()


def test_mismatched_checkpoint_gives_clear_error(full_run):
    full_dir, _ = full_run
    cfg = _cfg()
    cfg.agent.hidden_dim = 64
    with pytest.raises(ImssrError, match="different config .*agent.hidden_dim"):
        Trainer(cfg, str(full_dir), resume=True)


def test_nothing_to_resume(tmp_path):
    with pytest.raises(ImssrError, match="nothing to resume"):
        Trainer(_cfg(), str(tmp_path), resume=True)


def test_resume_drops_a_partially_written_log_line(tmp_path):
    from imssr.training.logger import CSVLog, TRAIN_COLUMNS

    log = CSVLog(str(tmp_path / "train.csv"), TRAIN_COLUMNS)
    log.write({"frame": 1000, "step": 125, "episode": 0, "critic_loss": 0.5})
    first = (tmp_path / "train.csv").read_bytes()
    log.write({"frame": 2000, "step": 250, "episode": 1})
    with open(tmp_path / "train.csv", "a") as fh:
        fh.write("3000,37")  # killed mid-line
    log.truncate_after(1000)
    assert [r["frame"] for r in read_csv(tmp_path / "train.csv")] == ["1000"]
    # The file a resume rewrites is byte for byte the one the run wrote, one line ending throughout.
    assert (tmp_path / "train.csv").read_bytes() == first and b"\r" not in first


def test_resume_with_changed_intervals_and_without_buffer(tmp_path):
    cfg = _cfg()
    cfg.train.save_buffer = False
    t = Trainer(cfg, str(tmp_path))
    try:
        train_stopped_at(t, 125)
    finally:
        t.close()
    cfg = _cfg()
    cfg.train.save_buffer = False
    cfg.train.eval_every_steps = 0  # changed on resume: no per-step evaluations, no hang
    cfg.train.checkpoint_every_steps = 0
    t = Trainer(cfg, str(tmp_path), resume=True)
    try:
        assert t.state.eval_schedule.next_step is None and t.state.ckpt_schedule.next_step is None
        assert t.state.learning_starts == 125 + 60  # refill the empty buffer with random actions first
        t.train()
    finally:
        t.close()
    assert t.frame == 2000 and t.agent.updates > 0
    assert [int(r["frame"]) for r in read_csv(tmp_path / "eval.csv")] == [1000, 2000]


def test_a_fresh_run_refuses_the_logs_of_a_run_that_never_checkpointed(tmp_path):
    (tmp_path / "train.csv").write_text("frame,step\n5000,625\n")
    (tmp_path / "eval.csv").write_text("frame,step\n5000,625\n")
    with pytest.raises(ImssrError, match=r"holds part of a run \(train.csv, eval.csv\) but no checkpoint to "
                                         r"resume from; choose another --out") as caught:
        Trainer(tiny_config("curl", steps=125, eval_every_steps=0), str(tmp_path))
    assert "--resume" not in str(caught.value)
    assert (tmp_path / "train.csv").read_text() == "frame,step\n5000,625\n"
    # What a sweep's fresh attempt does first: the run starts again from agent step 0.
    assert RunDir(str(tmp_path)).discard_unresumable() == ["train.csv", "eval.csv"]
    train_run(tiny_config("curl", steps=125, eval_every_steps=0), tmp_path)
    assert [r["frame"] for r in read_csv(tmp_path / "train.csv")] == ["1000"]
    assert [r["frame"] for r in read_csv(tmp_path / "eval.csv")] == ["1000"]


def test_a_fresh_run_starts_over_logs_without_rows_and_a_config_alone(tmp_path):
    """A training stopped before its first row, or a run a sweep described but never started."""
    (tmp_path / "train.csv").write_text("frame,step\n")
    RunDir(str(tmp_path)).write_config(tiny_config("curl", steps=125))
    assert RunDir(str(tmp_path)).run_parts() == []
    train_run(tiny_config("curl", steps=125, eval_every_steps=0), tmp_path)
    assert [r["frame"] for r in read_csv(tmp_path / "train.csv")] == ["1000"]


def test_agent_state_from_another_device_type_loads(full_run):
    _, full = full_run
    state = full.agent.state_dict()
    state["noise_gen"] = torch.zeros(16, dtype=torch.uint8)  # a CUDA generator's state size
    from imssr.agents import make_agent

    cfg = _cfg()
    other = make_agent((9, 100, 100), 1, cfg.agent, cfg.aux, cfg.intrinsic)
    other.load_state_dict(state)
    obs = np.zeros((9, 100, 100), np.uint8)
    assert np.array_equal(other.act(obs, True), full.agent.act(obs, True))


def test_checkpoint_from_before_new_settings_still_resumes(full_run, tmp_path):
    """A run saved before a setting existed resumes with that setting's default."""
    import shutil

    full_dir, _ = full_run
    shutil.copytree(full_dir, tmp_path / "old")
    path = RunDir(str(tmp_path / "old")).latest
    state = load_checkpoint(path).to_state()
    del state["config"]["env"]["footage_dir"], state["config"]["intrinsic"]["source"]
    torch.save(dict(state, format_version=1), path)
    seal_zip(path)
    cfg = _cfg()
    t = Trainer(cfg, str(tmp_path / "old"), resume=True)
    t.close()
    assert t.frame == 2000


def test_step_schedule_saves_itself_under_the_checkpoint_key_and_resumes():
    s = StepSchedule("eval", 100)
    assert not s.due(99) and s.due(100)
    s.advance(250)  # checked late (at an episode end): the next one after 250
    assert s.next_step == 300 and s.state_dict() == {"next_eval_step": 300}
    same = StepSchedule("eval", 100)
    same.load(300, step=260, saved_every=100)
    assert same.next_step == 300
    changed = StepSchedule("eval", 40)  # interval changed on resume: the next multiple of it
    changed.load(300, step=260, saved_every=100)
    assert changed.next_step == 280
    off = StepSchedule("ckpt", 0)
    assert off.next_step is None and not off.due(10**9) and off.state_dict() == {"next_ckpt_step": None}


def test_one_resume_rule_for_training_and_the_sweep():
    """RunConfig.resume_conflicts: what a resume may change (budget, device, TF32, what it
    evaluates and logs) and what it may not (anything that shapes the learning, and the precision
    that reports group runs by), one list for `imssr train --resume` and for the sweep; a
    setting the saved config lacks is its default."""
    from imssr.presets import make_config

    cfg = make_config("im-curl", "cartpole_swingup")
    saved = cfg.to_dict()
    later = copy.deepcopy(cfg)
    later.train.steps *= 2
    later.train.eval_episodes, later.agent.tf32, later.train.eval_video_format = 3, "true", "mp4"
    assert later.resume_conflicts(saved) == []
    later.agent.precision = "bf16"
    assert later.resume_conflicts(saved) == ["agent.precision"]
    later.agent.precision = "fp32"
    later.agent.critic_lr, later.train.seed = 5e-4, 9
    assert later.resume_conflicts(saved) == ["agent.critic_lr", "train.seed"]
    del saved["agent"]["critic_lr"]  # a config written before the setting existed: its default
    assert later.resume_conflicts(saved) == ["agent.critic_lr", "train.seed"]
    later.agent.critic_lr = type(cfg.agent)().critic_lr
    assert later.resume_conflicts(saved) == ["train.seed"]
