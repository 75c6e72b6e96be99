"""The training loop's parts, each on its own: the run state a checkpoint holds, the open
episode, progress lines, divergence, and the trainer's evaluation, checkpoint and stop steps."""
import ast
import inspect
import math
import re
import textwrap

import numpy as np
import pytest
import torch

from conftest import StopAtStep, a_checkpoint, tiny_config
from imssr.errors import DivergedError, NonFiniteError
from imssr.training import Trainer
from imssr.rundir.checkpoint import load_checkpoint
from imssr.training.divergence import first_non_finite
from imssr.training.loop import TrainingInterrupted
from imssr.training.progress import Eta, Progress, eval_summary, progress_line
from imssr.training.state import Episode, RunState

# The checkpoint keys of the loop's state: their names and meaning are the checkpoint format.
RUN_STATE_KEYS = {"frame", "step", "episode", "next_eval_step", "next_ckpt_step", "last_eval_step",
                  "learning_starts", "eval_history", "action_rng"}


# -- RunState ------------------------------------------------------------------------
def test_a_fresh_run_state_starts_at_step_0_with_its_schedules():
    s = RunState.fresh(eval_every=100, ckpt_every=0, seed_steps=60, action_seed=7)
    assert (s.frame, s.step, s.episode, s.last_eval_step, s.learning_starts) == (0, 0, 0, -1, 60)
    assert s.eval_schedule.next_step == 100 and s.ckpt_schedule.next_step is None
    assert s.eval_history == [] and s.last_return is None
    assert s.action_rng.uniform() == np.random.default_rng(7).uniform()


def test_run_state_saves_under_the_checkpoint_keys_and_loads_back():
    s = RunState.fresh(eval_every=100, ckpt_every=250, seed_steps=60, action_seed=7)
    s.frame, s.step, s.episode, s.last_eval_step = 2400, 300, 2, 300
    s.eval_schedule.advance(300)
    s.eval_history.append({"row": {"step": 300}, "returns": [1.0]})
    s.last_return = 12.5
    s.action_rng.uniform(size=5)
    state = s.state_dict()
    assert set(state) == RUN_STATE_KEYS
    assert (state["frame"], state["step"], state["episode"]) == (2400, 300, 2)
    assert (state["next_eval_step"], state["next_ckpt_step"], state["last_eval_step"]) == (400, 250, 300)
    assert state["learning_starts"] == 60 and state["action_rng"] == s.action_rng.bit_generator.state

    other = RunState.fresh(eval_every=100, ckpt_every=250, seed_steps=60, action_seed=99)
    other.load(a_checkpoint(**state), saved_eval_every=100, saved_ckpt_every=250)
    assert other.state_dict() == state
    assert other.eval_history is not s.eval_history  # a copy: the checkpoint's list stays as saved
    assert other.last_return is None  # per process, not saved
    assert other.action_rng.uniform() == s.action_rng.uniform()  # the same stream goes on


def test_run_state_load_restarts_a_schedule_whose_interval_changed_and_keeps_older_defaults():
    saved = RunState.fresh(eval_every=100, ckpt_every=250, seed_steps=60, action_seed=7)
    saved.step = 260
    state = dict(saved.state_dict(), next_eval_step=100, next_ckpt_step=250, last_eval_step=-1)
    state["learning_starts"] = None  # a checkpoint that does not hold it: the seed phase's end
    s = RunState.fresh(eval_every=40, ckpt_every=250, seed_steps=80, action_seed=7)
    s.load(a_checkpoint(**state), saved_eval_every=100, saved_ckpt_every=250)
    assert s.eval_schedule.next_step == 280 and s.ckpt_schedule.next_step == 250
    assert s.learning_starts == 80


# -- Episode -------------------------------------------------------------------------
def test_an_episode_sums_its_steps_and_metrics_into_its_train_row():
    ep = Episode(env_rng={"seed": 1})
    ep.add_step(np.array([0.5], np.float32), 1.5, 8)
    ep.add_step(np.array([-0.5], np.float32), 0.25, 8)
    ep.add_metrics({"critic_loss": torch.tensor(1.0), "alpha": torch.tensor(0.5)})
    ep.add_metrics({"critic_loss": torch.tensor(3.0), "alpha": torch.tensor(0.25)})
    row = ep.train_row(frame=1016, step=127, episode=3)
    assert (row["frame"], row["step"], row["episode"]) == (1016, 127, 3)
    assert row["episode_return"] == 1.75 and row["episode_frames"] == 16 and row["updates"] == 2
    assert row["critic_loss"] == 2.0 and row["alpha"] == 0.375
    assert row["fps"] > 0 and row["wall_time"] > 0
    assert list(row)[:8] == ["frame", "step", "episode", "episode_return", "episode_frames", "fps", "updates",
                             "wall_time"]


def test_an_episode_without_updates_has_no_metric_columns():
    ep = Episode(env_rng={})
    ep.add_step(np.zeros(1, np.float32), 0.0, 8)
    row = ep.train_row(8, 1, 0)
    assert row["updates"] == 0 and "critic_loss" not in row


def test_an_episode_round_trips_through_its_checkpoint_state():
    ep = Episode(env_rng={"state": [1, 2]})
    for i in range(3):
        ep.add_step(np.full(2, i / 4, np.float32), 0.5, 8)
        ep.add_metrics({"critic_loss": torch.tensor(0.1 * (i + 1))})
    state = ep.state_dict(action_dim=2)
    assert set(state) == {"env_rng", "actions", "return", "frames", "sums", "counts"}
    assert state["actions"].dtype == torch.float32 and state["actions"].shape == (3, 2)
    assert state["return"] == 1.5 and state["frames"] == 24 and state["counts"] == {"critic_loss": 3}
    assert isinstance(state["sums"]["critic_loss"], float)
    back = Episode.from_state_dict(state)
    assert back.env_rng == ep.env_rng and back.total_reward == ep.total_reward and back.frames == ep.frames
    assert [a.tolist() for a in back.actions] == [a.tolist() for a in ep.actions]
    assert back.sums["critic_loss"] == float(ep.sums["critic_loss"]) and back.counts == ep.counts
    back.add_metrics({"critic_loss": torch.tensor(1.0), "alpha": torch.tensor(0.5)})  # goes on summing
    assert back.counts == {"critic_loss": 4, "alpha": 1}


def test_an_episode_just_reset_saves_no_actions_of_the_action_shape():
    state = Episode(env_rng={}).state_dict(action_dim=6)
    assert state["actions"].shape == (0, 6) and state["sums"] == {} and state["counts"] == {}


# -- progress ------------------------------------------------------------------------
def test_progress_prints_a_line_when_due_where_no_bar_shows(capsys):
    p = Progress(total=10, step=4, frame=32, desc="x", bar=True, every_s=0.0)  # capsys: no terminal
    p.step(5, 40, None)
    p.step(6, 48, 12.25)
    p.say("eval step 6 frame 48: return 1.0 ± 0.0")
    p.close()
    out = capsys.readouterr().out.splitlines()
    assert re.fullmatch(r"imssr: agent step 5/10 \(50\.0%\), [\d,]+ frames/s, ETA after agent step 6, "
                        r"last episode return none yet", out[0]), out
    assert re.fullmatch(r"imssr: agent step 6/10 \(60\.0%\), [\d,]+ frames/s, ETA \d+:\d\d:\d\d, "
                        r"last episode return 12.2", out[1]), out
    assert out[2] == "eval step 6 frame 48: return 1.0 ± 0.0"


def test_progress_waits_every_s_between_lines(capsys):
    p = Progress(total=10, step=0, frame=0, desc="x", bar=True, every_s=3600.0)
    for i in range(1, 6):
        p.step(i, 8 * i, None)
    p.close()
    assert capsys.readouterr().out == ""


def test_progress_off_prints_no_line(capsys):
    """``train.progress=false`` (a notebook's ``progress=False``): no bar and no progress line,
    the evaluations' lines still."""
    p = Progress(total=10, step=0, frame=0, desc="x", bar=False, every_s=0.0)
    for i in range(1, 6):
        p.step(i, 8 * i, None)
    p.say("eval step 5 frame 40: return 1.0 ± 0.0")
    p.close()
    assert capsys.readouterr() == ("eval step 5 frame 40: return 1.0 ± 0.0\n", "")


def test_the_eta_comes_from_the_updates_not_the_seed_phase():
    """A run of 12,500 agent steps, updates from agent step 1,000: the seed phase runs at 100
    steps/s, the burst at agent step 1,000 takes 60 s, the updates run at 4 steps/s."""
    now = [0.0]
    eta = Eta(total=12_500, learning_starts=1000, clock=lambda: now[0])
    for step in range(1, 1001):  # the seed phase
        now[0] += 0.01
        eta.update(step)
        assert eta.seconds(step) is None and eta.text(step) == "after agent step 1,002"
    now[0] += 60.0 + 0.25  # agent step 1,001: the burst and the first update
    eta.update(1001)
    assert eta.text(1001) == "after agent step 1,002"
    for step in range(1002, 1102):
        now[0] += 0.25
        eta.update(step)
    # 100 agent steps in 25 s since agent step 1,001: the 11,399 left take 2,849.75 s.  The
    # whole run's rate (1,101 steps in 95 s) would have said 0:16:24.
    assert eta.seconds(1101) == pytest.approx(11_399 * 0.25) and eta.text(1101) == "0:47:30"
    assert eta.text(12_500) == "0:00:00"


def test_a_resumed_run_estimates_from_its_own_first_step():
    now = [100.0]
    eta = Eta(total=300, learning_starts=60, clock=lambda: now[0])
    eta.update(201)  # a resume at agent step 200
    assert eta.text(201) == "after agent step 202"
    now[0] += 3.0
    eta.update(202)
    assert eta.seconds(202) == pytest.approx(98 * 3.0)


def test_progress_line_and_eval_summary_texts():
    assert progress_line(1200, 500_000, 3100, 10.0, "13:51:20", 12.5) == (
        "imssr: agent step 1,200/500,000 (0.2%), 310 frames/s, ETA 13:51:20, last episode return 12.5")
    one = [{"mode": "train", "return_mean": 12.5, "return_std": 3.0}]
    assert eval_summary(one) == "12.5 ± 3.0"
    two = one + [{"mode": "color_hard", "return_mean": 1.0, "return_std": 0.5}]
    assert eval_summary(two) == "train 12.5 ± 3.0, color_hard 1.0 ± 0.5"


# -- divergence ----------------------------------------------------------------------
def test_first_non_finite_names_the_signal_before_the_losses():
    values = {"critic_loss": math.nan, "r_int_raw": math.inf, "alpha": 0.1, "zeta": -math.inf}
    names = {"r_int_raw": "intrinsic reward (CURL)"}
    assert first_non_finite(values, values, names) == "intrinsic reward (CURL) inf"
    del values["r_int_raw"]
    assert first_non_finite(values, values) == "critic loss nan"
    assert first_non_finite({"zeta": -math.inf, "alpha": 0.1}, ["zeta", "alpha"]) == "zeta -inf"
    assert first_non_finite({"alpha": 0.1, "step": 3}, ["alpha", "step"]) is None


# -- the trainer's steps -------------------------------------------------------------
@pytest.fixture
def trainer(tmp_path):
    # 125 agent steps an episode, evaluations and checkpoints every 125, a budget of 250.
    t = Trainer(tiny_config("curl", steps=250), str(tmp_path / "run"))
    t.begin()
    t.progress = _Progress()
    yield t
    t.close()


class _Calls:
    """Stands in for a trainer method and records its calls."""

    def __init__(self, result=None):
        self.calls, self.result = [], result

    def __call__(self, *args):
        self.calls.append(args)
        return self.result


class _Progress:
    """The loop's progress display: what it says, and the episode ends it is told of."""

    def __init__(self):
        self.lines, self.ended = [], []

    def say(self, text):
        self.lines.append(text)

    def step(self, step, frame, last_return):
        pass

    def episode_end(self, episode_return, fps, frame):
        self.ended.append((episode_return, frame))


class _Env:
    """The training env as :meth:`Trainer.end_step` sees it: each step 8 frames and a reward of
    1, the episode over when ``over``."""

    def __init__(self, over: bool = False):
        self.over = over

    def step(self, action):
        return np.zeros(1), 1.0, False, self.over, {"frame": None, "sim_steps": 8}

    def physics_state(self):
        return None


ROWS = [{"mode": "train", "return_mean": 3.0, "return_std": 1.0}]


def end_step_at(trainer, step: int, over: bool = False) -> None:
    """:meth:`Trainer.end_step` of agent step ``step`` (it ends at ``step + 1``) in an open
    episode, with :class:`_Env` and a replay buffer that takes anything."""
    trainer.env, trainer.replay = _Env(over), type("Replay", (), {"add": _Calls()})()
    trainer.state.step, trainer.state.frame = step, 8 * step
    trainer.episode, trainer.action = trainer.episode or Episode(env_rng={}), np.zeros(1, np.float32)
    trainer.end_step()


def test_an_evaluation_comes_at_the_schedule_and_moves_it_on(trainer):
    trainer.run_eval, s = _Calls(ROWS), trainer.state
    end_step_at(trainer, 123)
    assert trainer.run_eval.calls == [] and trainer.progress.lines == []
    end_step_at(trainer, 125)  # checked late: still due, and the next one is at 250
    assert len(trainer.run_eval.calls) == 1 and s.eval_schedule.next_step == 250
    assert trainer.progress.lines == ["eval step 126 frame 1008: return 3.0 ± 1.0"]


def test_the_final_evaluation_comes_once_at_the_end_of_the_budget(trainer):
    trainer.run_eval, trainer.save, trainer.logger.log_train, s = _Calls(ROWS), _Calls(), _Calls(), trainer.state
    s.eval_schedule.next_step = None
    end_step_at(trainer, 248, over=True)
    assert trainer.run_eval.calls == []
    s.last_eval_step = 250  # the periodic evaluation took this step
    end_step_at(trainer, 249, over=True)
    assert trainer.run_eval.calls == []
    s.last_eval_step = 125
    end_step_at(trainer, 249, over=True)
    assert len(trainer.run_eval.calls) == 1
    assert trainer.progress.lines == ["final eval step 250 frame 2000: return 3.0 ± 1.0"]


def test_a_checkpoint_comes_at_an_episode_end_at_the_schedule_and_at_the_end(trainer):
    trainer.save, trainer.run_eval, trainer.logger.log_train, s = _Calls(), _Calls(ROWS), _Calls(), trainer.state
    end_step_at(trainer, 123, over=True)
    assert trainer.save.calls == []
    end_step_at(trainer, 126)  # due, but not inside an episode
    assert trainer.save.calls == []
    end_step_at(trainer, 129, over=True)
    assert trainer.save.calls == [()] and s.ckpt_schedule.next_step == 250
    s.ckpt_schedule.next_step = None  # no periodic checkpoint: the last one still comes
    end_step_at(trainer, 249, over=True)
    assert len(trainer.save.calls) == 2


def test_a_stop_request_checkpoints_the_open_episode(trainer):
    s = trainer.state
    s.step = 40
    assert not trainer.stop_due()  # no request
    trainer.stop = StopAtStep(trainer, 40)
    assert trainer.stop_due()
    trainer.begin_step()
    trainer.episode.add_step(np.array([0.25], np.float32), 1.0, 8)
    trainer.save_for_stop()
    saved = load_checkpoint(trainer.run_dir.latest)
    assert saved.step == 40 and saved.episode_state["return"] == 1.0
    assert saved.episode_state["actions"].tolist() == [[0.25]]


def test_a_stop_request_does_not_save_twice_nor_past_the_budget(trainer):
    trainer.save, s = _Calls(), trainer.state
    trainer.stop = StopAtStep(trainer, 0)
    s.step, trainer.checkpoints.saved_step = 125, 125  # an episode end just checkpointed this step
    trainer.save_for_stop()
    assert trainer.save.calls == []
    s.step = 250  # the budget is spent: the run finishes instead
    assert not trainer.stop_due()


def test_a_stopped_training_says_how_to_continue(tmp_path):
    t = Trainer(tiny_config("curl", steps=250, seed_steps=100), str(tmp_path / "run"))
    t.stop = StopAtStep(t, 40)
    try:
        with pytest.raises(TrainingInterrupted, match=r"^stopped at agent step 40 by SIGTERM; continue with: "
                                                      r"imssr train --out \S+ --resume$"):
            t.train()
    finally:
        t.close()


def test_an_episode_end_logs_its_row_or_raises_on_a_non_finite_metric(trainer):
    s, said = trainer.state, trainer.progress
    trainer.episode = ep = Episode(env_rng={})
    ep.add_step(np.zeros(1, np.float32), 2.5, 1000)
    ep.add_metrics({"critic_loss": torch.tensor(1.0)})
    trainer.logger.log_train = _Calls()
    end_step_at(trainer, 124, over=True)
    (row,), = trainer.logger.log_train.calls
    assert row["episode"] == 0 and row["episode_return"] == 3.5 and row["critic_loss"] == 1.0
    assert s.episode == 1 and s.last_return == 3.5 and said.ended == [(3.5, 1000)] and trainer.episode is None
    trainer.episode = ep = Episode(env_rng={})
    ep.add_metrics({"critic_loss": torch.tensor(math.nan)})
    with pytest.raises(DivergedError, match="^critic loss nan$"):
        end_step_at(trainer, 124, over=True)
    assert s.episode == 1 and len(trainer.logger.log_train.calls) == 1


def test_a_divergence_names_the_open_episodes_first_non_finite_metric(trainer):
    ep = Episode(env_rng={})
    ep.add_metrics({"critic_loss": torch.tensor(math.inf), "actor_loss": torch.tensor(math.nan)})
    assert trainer.divergence.describe(NonFiniteError("intrinsic signal nan"), ep) == "critic loss inf"
    ep = Episode(env_rng={})
    ep.add_metrics({"critic_loss": torch.tensor(1.0)})
    assert trainer.divergence.describe(NonFiniteError("intrinsic signal nan"), ep) == "intrinsic signal nan"
    assert trainer.divergence.describe(DivergedError("action [nan]"), None) == "action [nan]"


def test_seed_phase_actions_come_from_the_loop_generator_then_the_agent_learns(trainer):
    s = trainer.state
    expected = np.random.default_rng(np.random.SeedSequence(trainer.cfg.train.seed).spawn(2)[1])
    assert not trainer.begin_step()  # the seed phase: no policy action
    assert np.array_equal(trainer.action, expected.uniform(-1.0, 1.0, 1).astype(np.float32))
    assert trainer.replay.size == 1  # the reset's frame
    trainer.agent.update = _Calls({"critic_loss": torch.tensor(0.5)})
    trainer.learn(lambda: trainer.episode.add_metrics(trainer.agent.update()))
    assert trainer.agent.update.calls == [] and trainer.episode.counts == {}
    trainer.end_step()
    assert (s.step, s.frame, trainer.episode.frames) == (1, 8, 8)
    assert trainer.replay.size == 2  # the reset's frame and this step's
    s.learning_starts = 0  # an agent with a batch to learn from: one update
    assert trainer.begin_step()  # the policy acts
    trainer.learn(lambda: trainer.episode.add_metrics(trainer.agent.update()))
    assert len(trainer.agent.update.calls) == 1 and trainer.episode.counts == {"critic_loss": 1}


def test_the_burst_runs_once_when_the_first_seed_phase_ends(trainer):
    trainer.cfg.train.burst_updates = 3
    update = _Calls()
    trainer.state.step = trainer.state.learning_starts = trainer.cfg.train.seed_steps
    trainer.learn(update)
    trainer.state.step += 1
    trainer.learn(update)
    assert len(update.calls) == 4


def test_a_non_finite_action_stops_the_run_before_the_simulator_sees_it(trainer):
    with pytest.raises(DivergedError, match="^action nan$"):
        trainer.take_action(np.array([np.nan], np.float32))


def test_the_trainer_stays_small():
    """Trainer holds the loop and its public steps (which the lockstep loop of many seeds,
    :class:`imssr.training.seeds.SeedsTrainer`, takes for every seed) and the progress of its long
    phases (:meth:`Trainer.phase`); checkpointing, building, the stop request and how progress
    shows live in modules of their own: at most 280 lines."""
    assert len(inspect.getsource(Trainer).splitlines()) <= 280


def test_the_training_loop_stays_short():
    """Trainer.train reads top to bottom: at most 50 lines besides its docstring."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(Trainer.train)))
    body = tree.body[0].body
    start = body[1].lineno if isinstance(body[0], ast.Expr) else body[0].lineno
    assert body[-1].end_lineno - start + 1 <= 50


def test_a_training_interrupted_crosses_a_process_boundary_whole():
    import pickle

    exc = TrainingInterrupted("stopped at agent step 40 by SIGTERM; continue with: ...", 40, "runs/x")
    back = pickle.loads(pickle.dumps(exc))
    assert (str(back), back.step, back.out) == (str(exc), 40, "runs/x")
