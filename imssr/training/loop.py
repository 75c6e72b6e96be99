"""The training loop: seed phase, updates, evaluation, logging, checkpoints.

Counters: ``frame`` counts environment (simulator) frames, ``step`` counts
agent steps (``frame = step * action_repeat``).  The budget, evaluation and
checkpoint intervals and the beta schedule count agent steps, as the authors'
code does; every log carries both counters.
Checkpoints are taken at episode ends, where the next thing the loop does is a
reset from the saved task RNG, so ``--resume`` reproduces the uninterrupted run.
"""
from __future__ import annotations

import math
import os
import signal
import sys
import threading
import time
from collections import defaultdict
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
from tqdm import tqdm

from imssr._gl import gl_renderer, software_rendering_warning
from imssr.config import RunConfig, steps_for_frames
from imssr.data import FOOTAGE_DIR_ENV, IMAGE_DIR_ENV
from imssr.envs import env_from_config
from imssr.errors import DIVERGED_PREFIX, DivergedError, ImssrError, NonFiniteError
from imssr.plots.curves import plot_learning_curve
from imssr.presets import get_algo
from imssr.replay import make_replay_buffer, replay_placement
from imssr.replay.buffer import ReplayFileError
from imssr.rundir import RunDir
from imssr.seeds import TRAINING_EVAL_SEED_OFFSET
from imssr.training.build import build_agent, resolve_device
from imssr.training.evaluate import eval_row, evaluate, non_finite_text
from imssr.training.logger import Logger
from imssr.utils import contention_warning, rng_states, seed_everything, set_rng_states

# Settings that may change between a run and its resume.
RESUMABLE_CHANGES = {"train.steps", "train.device", "train.replay_device", "train.progress",
                     "train.tensorboard", "agent.precision", "agent.tf32", "agent.compile",
                     "train.torch_threads", "train.eval_episodes", "train.eval_every_steps",
                     "train.checkpoint_every_steps", "train.eval_modes", "train.save_buffer",
                     "train.wandb", "train.wandb_project", "train.wandb_group", "train.eval_video_every",
                     "train.eval_video_format"}

PROGRESS_EVERY_S = 60.0
"""Seconds of wall time between progress lines when stdout is not a terminal (a SLURM or nohup
log): agent step, frames per second, ETA and the last episode's return."""
# Training metrics in the order a divergence names them: the raw intrinsic signal (its mean), which
# enters the critic's target within the same update, then the critic's loss.
DIVERGENCE_ORDER = ("r_int_raw", "critic_loss", "actor_loss", "alpha_loss", "aux_loss", "rnd_loss", "q_mean",
                    "alpha", "entropy")


@dataclass
class StepSchedule:
    """An event every ``every`` agent steps (0: never): due at the first agent step checked at or
    past ``next_step``.  It saves itself under ``next_<name>_step``, the checkpoint key imssr has
    always used, so older checkpoints resume."""

    name: str
    """``eval`` or ``ckpt``: names the checkpoint key."""
    every: int
    """Agent steps between two events; 0 turns the event off."""
    next_step: Optional[int] = None
    """The agent step at or after which the event is next due; None when off."""

    def __post_init__(self):
        if self.next_step is None and self.every:
            self.next_step = self.every

    @property
    def key(self) -> str:
        return f"next_{self.name}_step"

    def due(self, step: int) -> bool:
        return self.next_step is not None and step >= self.next_step

    def advance(self, step: int) -> None:
        """Move past ``step``: the next event falls on the first multiple after it of the schedule."""
        while self.due(step):
            self.next_step += self.every

    def state_dict(self) -> dict:
        return {self.key: self.next_step}

    def load_state_dict(self, counters: dict, step: int, saved_every: int) -> None:
        """Resume at agent step ``step``: the saved next step if the interval is unchanged
        (``saved_every``), else the first multiple of the new interval after ``step``."""
        self.next_step = counters[self.key] if saved_every == self.every else _next_multiple(step, self.every)


class TrainingInterrupted(Exception):
    """Training stopped on a signal after checkpointing its last agent step; the message is the
    line the CLI prints ("stopped at agent step N by SIGTERM; continue with: ...")."""


class StopRequest:
    """SIGTERM / SIGINT as a request to stop after the current agent step (SLURM sends SIGTERM
    on preemption and at the time limit, some seconds before SIGKILL).

    The first signal is recorded in :attr:`signal_name` and the default handlers come back, so
    a second signal ends the process at once: SIGTERM kills it, SIGINT raises
    ``KeyboardInterrupt``.  Checkpoint writes are atomic, so neither damages the last
    checkpoint.  Handlers are installed only on the main thread (Python's rule)."""

    SIGNALS = (signal.SIGTERM, signal.SIGINT)

    def __init__(self):
        self.signal_name: Optional[str] = None
        self._previous: dict = {}

    def install(self) -> "StopRequest":
        if threading.current_thread() is threading.main_thread():
            for signum in self.SIGNALS:
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def _handle(self, signum, frame) -> None:
        self.signal_name = signal.Signals(signum).name
        # os.write, not print: a signal handler may run inside a print to the same stream.
        os.write(2, f"imssr: {self.signal_name}: stopping after this agent step with a checkpoint "
                    "(a second signal stops at once)\n".encode())
        for sig in self.SIGNALS:  # the next signal acts at once
            signal.signal(sig, signal.default_int_handler if sig == signal.SIGINT else signal.SIG_DFL)

    def uninstall(self) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        out.update(_flatten(v, key + ".") if isinstance(v, dict) else {key: v})
    return out


class Trainer:
    """Trains one run into ``out_dir``.

    Args:
        cfg: the run's configuration.
        out_dir: run directory (config.json, CSV logs, checkpoints, tb/).
        resume: continue from ``out_dir/checkpoints/latest.pt`` (or, when it is damaged, from
            the newest retained ``step-*.pt`` that verifies).
        refill_buffer: on resume, when the saved replay buffer is missing or damaged, start
            with an empty buffer refilled by random actions (not an exact resume) instead of
            failing.
        stop: the SIGTERM / SIGINT request the CLI installed (:class:`StopRequest`); when it is
            set, :meth:`train` checkpoints after the current agent step and raises
            :class:`TrainingInterrupted`.

    The trainer holds an exclusive lock on ``out_dir`` (:mod:`imssr.training.lock`) from
    before it writes or deletes anything there until :meth:`close`.
    """

    def __init__(self, cfg: RunConfig, out_dir: str, resume: bool = False, refill_buffer: bool = False,
                 stop: Optional[StopRequest] = None):
        if os.path.exists(out_dir) and not os.path.isdir(out_dir):
            raise ImssrError(f"--out {out_dir} is a file, not a directory")
        # A second process on the same directory fails here, before the Logger of a fresh
        # run deletes the first one's logs and tb/.
        self.run_dir = RunDir(out_dir)
        self._lock = self.run_dir.open()
        self.refill_buffer = refill_buffer
        self.stop = stop or StopRequest()  # uninstalled: never set
        # The open episode, so that a stop mid-episode can checkpoint it (see _episode_state).
        self._episode_env_rng: Optional[dict] = None
        self._episode_actions: list[np.ndarray] = []
        self._resume_episode: Optional[dict] = None
        self._replay_file: Optional[str] = None  # the replay file that latest.pt names
        self.resumed_from: Optional[str] = None
        self._fallback = False
        try:
            self._setup(cfg, out_dir, resume)
        except BaseException:
            self.close()
            raise

    def _setup(self, cfg: RunConfig, out_dir: str, resume: bool) -> None:
        if not resume:
            # Sources named by environment variables are written into the run's
            # config, so a resume or `imssr evaluate` in another shell uses the same.
            cfg.aux.image_dir = cfg.aux.image_dir or os.environ.get(IMAGE_DIR_ENV, "")
            cfg.env.footage_dir = cfg.env.footage_dir or os.environ.get(FOOTAGE_DIR_ENV, "")
        cfg.validate()
        get_algo(cfg.algo)
        self.cfg, self.out_dir = cfg, out_dir
        self.device = resolve_device(cfg.train.device)
        self.replay_placement = replay_placement(cfg.train.replay_device, self.device,
                                                 cfg.train.replay_capacity * 3 * cfg.env.image_size ** 2)
        ckpt = None
        if resume:
            ckpt = self._check_resume()
            if ckpt["step"] > cfg.train.steps:
                # Refused before anything (config.json) is rewritten with the smaller budget.
                raise ImssrError(f"the run in {out_dir} is already at agent step {ckpt['step']:,}, past the "
                                 f"budget of {cfg.train.steps:,} steps asked for; resume with --steps "
                                 f"{ckpt['step']} or more")
        elif self.run_dir.has_run():
            raise ImssrError(f"{out_dir} already holds a run; pass --resume to continue it "
                             "or choose another --out")
        if cfg.train.torch_threads:
            torch.set_num_threads(cfg.train.torch_threads)
        warning = contention_warning(torch.get_num_threads())
        if warning:
            print(warning, flush=True)
        if ckpt is not None:
            warning = thread_warning(ckpt.get("torch_threads"), torch.get_num_threads(), self.device)
            if warning:
                print(warning, flush=True)
        seed_everything(cfg.train.seed)
        e = cfg.env
        # Training footage and evaluation footage come from disjoint pools.
        self.env = env_from_config(e, seed=cfg.train.seed, footage_split="train")
        self.eval_modes = cfg.train.eval_mode_list(e.mode)
        self.eval_envs = {m: env_from_config(e, seed=cfg.train.seed + TRAINING_EVAL_SEED_OFFSET, mode=m,
                                             footage_split="test")
                          for m in self.eval_modes}
        if torch.cuda.is_available():
            warning = software_rendering_warning(os.environ.get("MUJOCO_GL", "egl"),
                                                 gl_renderer(self.env.physics), gpu=True)
            if warning:
                print(warning, flush=True)
        self.action_dim = self.env.action_space.shape[0]
        self.agent = build_agent(cfg, self.env.observation_space.shape, self.action_dim, self.device)
        if self.agent.aux is not None:
            # SODA's overlay images: a bad folder fails now, not after the seed phase.
            self.agent.aux.load_data(self.device)
        # Independent streams for the replay sampler and the seed-phase actions.
        replay_seq, action_seq = np.random.SeedSequence(cfg.train.seed).spawn(2)
        # Each frame's physics state goes in too (float64 qpos and qvel: 32 bytes for cartpole,
        # 144 for walker): `imssr analyze` renders it again.
        if self.replay_placement.reason:
            print(self.replay_placement.reason, flush=True)
        self.replay = make_replay_buffer(self.replay_placement.device, cfg.train.replay_capacity,
                                         (3, e.image_size, e.image_size), self.action_dim, e.frame_stack,
                                         seed=replay_seq, physics_dim=self.env.physics_state_dim)
        self.action_rng = np.random.default_rng(action_seq)
        self.frame = self.step = self.episode = 0
        self.eval_schedule = StepSchedule("eval", cfg.train.eval_every_steps)
        self.ckpt_schedule = StepSchedule("ckpt", cfg.train.checkpoint_every_steps)
        self.last_eval_step = -1
        # Agent step from which the agent acts and learns (later after a resume
        # without a saved buffer: the buffer refills with random actions first).
        self.learning_starts = cfg.train.seed_steps
        self.eval_history: list[dict] = []
        os.makedirs(out_dir, exist_ok=True)
        if ckpt is not None:
            self._restore(ckpt)
        self.run_dir.write_config(cfg)
        wandb = None
        if cfg.train.wandb:
            # Imported here: W&B is an extra, and a run without it must not load it.
            from imssr.training.wandb_run import WandbRun

            wandb = WandbRun(cfg, out_dir, resume=ckpt is not None, warn=lambda text: print(text, flush=True))
        self.logger = Logger(out_dir, cfg.train.tensorboard, resume_frame=self.frame if ckpt else None,
                             wandb=wandb)
        if ckpt is not None and "next_eval_step" not in ckpt:
            print(f"imssr: resuming a run made before budgets counted agent steps: its budget is "
                  f"{cfg.budget_text()}", flush=True)
        if ckpt is not None:
            # The checkpoint's evaluation history is authoritative for eval logs.
            self.logger.rewrite_eval(self.eval_history)
            print(f"imssr: resuming from agent step {self.step:,} (frame {self.frame:,}) of "
                  f"{cfg.train.steps:,}", flush=True)

    # -- resume ------------------------------------------------------------------
    def _check_resume(self) -> dict:
        ckpt, path, note = self.run_dir.usable_checkpoint()
        if note:
            print(f"imssr: {note}", flush=True)
        self.resumed_from, self._fallback = path, path != self.run_dir.latest
        # Through the config class, so settings added since the run started read as defaults.
        try:
            saved = _flatten(RunConfig.from_dict(ckpt["config"]).to_dict())
        except (ImssrError, TypeError):
            saved = _flatten(ckpt["config"])
        now = _flatten(self.cfg.to_dict())
        diff = sorted(k for k in saved.keys() | now.keys()
                      if saved.get(k) != now.get(k) and k not in RESUMABLE_CHANGES)
        if diff:
            raise ImssrError(f"checkpoint {path} was made with a different config ({', '.join(diff[:5])}"
                             f"{', ...' if len(diff) > 5 else ''}); resume with the run's own settings")
        return ckpt

    def _restore(self, ckpt: dict) -> None:
        try:
            self.agent.load_state_dict(ckpt["agent"])
        except (RuntimeError, KeyError, ValueError) as exc:
            raise ImssrError(f"checkpoint does not match this agent: {str(exc).splitlines()[0]}") from None
        self.frame, self.step, self.episode = ckpt["frame"], ckpt["step"], ckpt["episode"]
        self.learning_starts = ckpt.get("learning_starts", self.cfg.train.seed_steps)
        self.eval_history = list(ckpt.get("eval_history", []))
        counters = _step_counters(ckpt, self.cfg.env.action_repeat)
        self.last_eval_step = counters["last_eval_step"]
        saved_train = RunConfig.from_dict(ckpt["config"]).train
        # Intervals may change on resume: keep the saved schedule only when they did not.
        self.eval_schedule.load_state_dict(counters, self.step, saved_train.eval_every_steps)
        self.ckpt_schedule.load_state_dict(counters, self.step, saved_train.checkpoint_every_steps)
        self.env.set_rng_state(ckpt["env_rng"])
        saved = ckpt.get("eval_env_rngs") or {self.cfg.env.mode: ckpt.get("eval_env_rng")}
        for mode, env in self.eval_envs.items():
            if saved.get(mode) is not None:  # a scene added on resume starts from its seed
                env.set_rng_state(saved[mode])
        self.action_rng.bit_generator.state = ckpt["action_rng"]
        set_rng_states(ckpt["global_rng"])
        refill = None if ckpt.get("replay_file") else "checkpoint holds no replay buffer"
        if ckpt.get("replay_file"):
            path, frames = self.run_dir.replay_files(ckpt["replay_file"])
            try:
                self.replay.load(path, ckpt["replay_state"]["rng"])
            except ReplayFileError as exc:
                # Only latest.pt's replay buffer is kept: an older checkpoint resumes without one.
                if self._fallback and not (os.path.exists(path) and os.path.exists(frames)):
                    refill = f"no replay buffer was kept for {os.path.basename(self.resumed_from)}"
                elif self.refill_buffer:
                    refill = str(exc)
                else:
                    raise ImssrError(f"{exc}; `imssr train --resume --refill-buffer` continues with an empty "
                                     "buffer refilled by random actions (not an exact resume)") from None
            else:
                if self.replay.state_dict()["head"] != ckpt["replay_state"]["head"]:
                    raise ImssrError(f"replay buffer {path} does not match the checkpoint")
                self._replay_file = ckpt["replay_file"]
        if ckpt.get("episode_state") is not None and not refill:
            # Stopped mid-episode: train() rebuilds the open episode before it continues.
            self._resume_episode = ckpt["episode_state"]
        if refill:
            self.learning_starts = self.step + max(self.cfg.train.seed_steps, self.cfg.agent.batch_size)
            print(f"imssr: warning: {refill}; refilling it with random "
                  f"actions until agent step {self.learning_starts} (the resume is not exact)", flush=True)

    def save(self, episode: Optional[dict] = None) -> None:
        """Checkpoint now (``episode``: the open episode's state, :meth:`_episode_state`, when
        stopping mid-episode).  A save that fails (a full disk) leaves the previous checkpoint as
        it was and removes the replay files it wrote, which no checkpoint names."""
        latest = self.run_dir.latest
        before = _identity(latest)
        try:
            self._save(episode)
        except ImssrError:
            replay_file = self.run_dir.replay_name(self.step)
            if (self.cfg.train.save_buffer and replay_file != self._replay_file
                    and _identity(latest) == before):
                for p in self.run_dir.replay_files(replay_file):
                    if os.path.exists(p):
                        os.unlink(p)
            raise
        self._replay_file = self.run_dir.replay_name(self.step) if self.cfg.train.save_buffer else None
        self._saved_step = self.step

    def _episode_state(self, ep_return: float, ep_frames: int, sums: dict, counts: dict) -> dict:
        """The open episode as a checkpoint holds it: the env's RNG state at its reset and the
        actions since, from which :meth:`_rebuild_episode` steps the env to where it stopped
        (physics, scene and frame stack bit for bit, without storing simulator internals), and
        the episode's sums so far.  Its transitions are in the saved replay buffer already."""
        actions = (np.stack(self._episode_actions) if self._episode_actions
                   else np.zeros((0, self.action_dim), np.float32))
        return {"env_rng": self._episode_env_rng, "actions": torch.from_numpy(actions.astype(np.float32)),
                "return": float(ep_return), "frames": int(ep_frames),
                # Floats: the same values as the float32 sums (exact in float64), on any device.
                "sums": {k: float(v) for k, v in sums.items()}, "counts": dict(counts)}

    def _rebuild_episode(self, state: dict):
        """Step the env through the saved open episode; returns its current observation."""
        saved_rng = self.env.get_rng_state()
        self.env.set_rng_state(state["env_rng"])
        obs, _ = self.env.reset()
        actions = state["actions"].numpy()
        for action in actions:
            obs, *_ = self.env.step(action)
        if self.env.get_rng_state() != saved_rng:
            raise ImssrError(f"cannot rebuild the episode open in {self.resumed_from}: the environment's "
                             "random state differs from the saved one")
        self._episode_env_rng, self._episode_actions = state["env_rng"], list(actions)
        return obs

    def _save(self, episode: Optional[dict] = None) -> None:
        replay_file = None
        if self.cfg.train.save_buffer:
            replay_file = self.run_dir.replay_name(self.step)
            self.replay.save(self.run_dir.replay_path(replay_file))
        state = {
            "config": self.cfg.to_dict(), "frame": self.frame, "step": self.step,
            "episode": self.episode, "agent": self.agent.state_dict(),
            **self.eval_schedule.state_dict(), **self.ckpt_schedule.state_dict(),
            "last_eval_step": self.last_eval_step, "learning_starts": self.learning_starts,
            "eval_history": self.eval_history,
            "env_rng": self.env.get_rng_state(), "eval_env_rngs": {m: env.get_rng_state() for m, env in self.eval_envs.items()},
            "action_rng": self.action_rng.bit_generator.state, "global_rng": rng_states(),
            "replay_file": replay_file, "replay_state": self.replay.state_dict(),
            # A resume with another thread count is valid but not bit-identical (thread_warning).
            "torch_threads": torch.get_num_threads(),
            "episode_state": episode,
        }
        self.run_dir.save_checkpoint(state, keep=self.cfg.train.keep_checkpoints)

    # -- the loop ----------------------------------------------------------------
    @property
    def eval_env(self):
        """The evaluation env of the first evaluated scene."""
        return self.eval_envs[self.eval_modes[0]]

    def run_eval(self) -> list[dict]:
        """Evaluate in every scene of ``train.eval_modes``; one ``eval.csv`` row each.  At every
        ``train.eval_video_every``-th evaluation, the first episode of each scene is recorded
        (the frames the evaluation renders anyway, so the returns do not change)."""
        t = self.cfg.train
        # This evaluation's number, counted from the history so that a resume keeps the rhythm.
        number = len({item["row"]["step"] for item in self.eval_history}) + 1
        record = t.eval_video_every > 0 and number % t.eval_video_every == 0
        rows = []
        for mode, env in self.eval_envs.items():
            frames: Optional[list] = [] if record else None
            returns = evaluate(self.agent, env, t.eval_episodes, record=frames)
            row = dict(eval_row(self.frame, self.step, mode, returns), wall_time=time.time())
            self.logger.log_eval(row, returns)
            if frames:
                self.logger.log_video(mode, frames, self.frame, self.step, t.eval_video_format)
            self.eval_history.append({"row": row, "returns": returns})
            rows.append(row)
        self.last_eval_step = self.step
        return rows

    progress_every_s: float = PROGRESS_EVERY_S
    """Seconds between progress lines when stdout is not a terminal (see :data:`PROGRESS_EVERY_S`)."""

    def train(self, stop_at_step: Optional[int] = None) -> None:
        """Train to ``cfg.train.steps`` agent steps.  ``stop_at_step`` stops early after the
        first checkpoint at or past it, as a killed process would (for tests).

        A NaN or infinite action (checked on the host before the simulator sees it), training
        metric (checked once per episode, with the episode's metrics) or intrinsic signal stops
        the run with :class:`DivergedError` ("diverged at agent step N: critic loss nan"); the
        last checkpoint is from before it, since nothing is saved after a divergence.
        """
        cfg, t = self.cfg, self.cfg.train
        total_steps = cfg.total_steps
        bar = tqdm(total=total_steps, initial=min(self.step, total_steps), unit="step",
                   disable=None if t.progress else True, dynamic_ncols=True,
                   desc=f"{cfg.algo} {cfg.env.task} s{t.seed}")
        need_reset, obs = True, None
        ep_return, ep_frames, ep_start = 0.0, 0, time.time()
        sums: dict[str, float] = defaultdict(float)
        counts: dict[str, int] = defaultdict(int)
        # A line every progress_every_s seconds where no progress bar shows (a log file).
        log_progress = bar.disable and not _isatty(sys.stdout)
        started, start_step, start_frame = time.monotonic(), self.step, self.frame
        next_progress, last_return = started + self.progress_every_s, None
        self._saved_step = -1
        if self._resume_episode is not None:
            ep = self._resume_episode
            obs, need_reset = self._rebuild_episode(ep), False
            ep_return, ep_frames = ep["return"], ep["frames"]
            sums.update(ep["sums"])
            counts.update(ep["counts"])
            self._resume_episode = None
        try:
            while self.step < total_steps:
                if need_reset:
                    self._episode_env_rng, self._episode_actions = self.env.get_rng_state(), []
                    obs, info = self.env.reset()
                    self.replay.add_first(info["frame"], self.env.physics_state(), self.step)
                    need_reset, ep_return, ep_frames, ep_start = False, 0.0, 0, time.time()
                    sums.clear(); counts.clear()
                if self.step < self.learning_starts:
                    action = self.action_rng.uniform(-1.0, 1.0, self.action_dim).astype(np.float32)
                else:
                    action = self.agent.act(obs, deterministic=False)
                    if not np.isfinite(action).all():  # a few host values: no device sync
                        raise DivergedError(f"action {non_finite_text(action)}")
                    # The burst: once, when the first seed phase ends (not after a refill).
                    n_updates = max(1, t.burst_updates) if self.step == t.seed_steps else 1
                    for _ in range(n_updates):
                        for k, v in self.agent.update(self.replay, self.step).items():
                            sums[k] += v; counts[k] += 1
                obs, reward, terminated, truncated, info = self.env.step(action)
                self._episode_actions.append(action)
                self.replay.add(action, reward, 0.0 if terminated else 1.0, info["frame"],
                                self.env.physics_state(), self.step + 1)
                self.step += 1
                self.frame += info["sim_steps"]
                ep_return += reward
                ep_frames += info["sim_steps"]
                bar.update(1)
                if log_progress and time.monotonic() >= next_progress:
                    now = time.monotonic()
                    next_progress = now + self.progress_every_s
                    print(_progress_line(self.step, total_steps, self.frame - start_frame,
                                         self.step - start_step, now - started, last_return), flush=True)
                if self.eval_schedule.due(self.step):
                    rows = self.run_eval()
                    self.eval_schedule.advance(self.step)
                    _say(bar, f"eval step {self.step} frame {self.frame}: return " + _summary(rows))
                if terminated or truncated:
                    dt = max(time.time() - ep_start, 1e-9)
                    row = {"frame": self.frame, "step": self.step, "episode": self.episode,
                           "episode_return": ep_return, "episode_frames": ep_frames,
                           "fps": ep_frames / dt, "updates": counts.get("critic_loss", 0),
                           "wall_time": time.time()}
                    # One host sync per episode, not one per metric per update.
                    row.update({k: float(sums[k]) / counts[k] for k in sums})
                    bad = _first_non_finite(row, sums, self._metric_names())
                    if bad:
                        raise DivergedError(bad)
                    self.logger.log_train(row)
                    last_return = ep_return
                    bar.set_postfix(ret=f"{ep_return:.1f}", fps=f"{ep_frames / dt:.0f}", frame=self.frame)
                    self.episode += 1
                    need_reset = True
                    last = self.step >= total_steps
                    if last and self.last_eval_step != self.step:
                        rows = self.run_eval()
                        _say(bar, f"final eval step {self.step} frame {self.frame}: return " + _summary(rows))
                    if last or self.ckpt_schedule.due(self.step):
                        self.ckpt_schedule.advance(self.step)
                        self.save()
                        if stop_at_step is not None and self.step >= stop_at_step and not last:
                            return
                if self.stop.signal_name is not None and self.step < total_steps:
                    # A periodic checkpoint (with the replay buffer) of this agent step, unless
                    # the episode's end just wrote one.
                    if self._saved_step != self.step:
                        self.save(None if need_reset else self._episode_state(ep_return, ep_frames, sums, counts))
                    raise TrainingInterrupted(
                        f"stopped at agent step {self.step} by {self.stop.signal_name}; "
                        f"continue with: imssr train --out {self.out_dir} --resume")
            if not need_reset:
                # Budget ended mid-episode: evaluate and checkpoint what we have.
                if self.last_eval_step != self.step:
                    self.run_eval()
                self.save()
            if self.logger.wants_media:
                self.logger.log_image("learning_curve", plot_learning_curve(self.out_dir), self.frame, self.step)
        except NonFiniteError as exc:
            # Named by the first non-finite training metric of the episode so far (one host
            # sync, only now), else by what was found (the action, the intrinsic signal).
            what = _first_non_finite({k: float(v) for k, v in sums.items()}, sums, self._metric_names()) or str(exc)
            raise DivergedError(f"{DIVERGED_PREFIX} {self.step}: {what}") from None
        finally:
            bar.close()
            self.logger.close()

    def _metric_names(self) -> dict[str, str]:
        """How a divergence names the metrics that are not named by their key."""
        signal = self.agent.signal
        return {"r_int_raw": f"intrinsic reward ({signal.label})"} if signal is not None else {}

    def close(self) -> None:
        """Close the envs and release the run directory (also after a failed ``__init__``)."""
        try:
            if getattr(self, "env", None) is not None:
                self.env.close()
            for env in getattr(self, "eval_envs", {}).values():
                env.close()
        finally:
            self._lock.release()


def _identity(path: str) -> Optional[tuple]:
    """Which file ``path`` is now (None if none): tells whether a save replaced it."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return None
    return st.st_ino, st.st_mtime_ns, st.st_size


def thread_warning(saved: Optional[int], now: int, device) -> Optional[str]:
    """A one-line warning when a CPU run resumes with another torch thread count than it was
    trained with (None when equal, unknown, or on a GPU): CPU kernels split their reductions
    by thread, so float sums round differently and the run drifts from the uninterrupted one."""
    if saved is None or saved == now or torch.device(device).type != "cpu":
        return None
    return (f"imssr: warning: this run was trained with {saved} torch thread(s) and resumes with {now}: "
            "it stays valid but is no longer bit-identical to an uninterrupted run "
            f"(--set train.torch_threads={saved} keeps it exact)")


def _first_non_finite(values: dict, keys, names: Optional[dict[str, str]] = None) -> Optional[str]:
    """``"critic loss nan"`` for the first of ``keys`` (in :data:`DIVERGENCE_ORDER`, then the
    rest) whose value in ``values`` is NaN or infinite, named as in ``names`` or by its key;
    None when all are finite."""
    ordered = [k for k in DIVERGENCE_ORDER if k in keys] + sorted(k for k in keys if k not in DIVERGENCE_ORDER)
    for k in ordered:
        v = values.get(k)
        if isinstance(v, float) and not math.isfinite(v):
            return f"{(names or {}).get(k, k.replace('_', ' '))} {v}"
    return None


def _isatty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


def _progress_line(step: int, total: int, frames: int, steps: int, seconds: float,
                   last_return: Optional[float]) -> str:
    """``imssr: agent step 1,200/500,000 (0.2%), 310 frames/s, ETA 3:12:40, last episode return 12.5``:
    rates over this process's training so far."""
    seconds = max(seconds, 1e-9)
    eta = "unknown" if steps <= 0 else _hms((total - step) * seconds / steps)
    ret = "none yet" if last_return is None else f"{last_return:.1f}"
    return (f"imssr: agent step {step:,}/{total:,} ({100 * step / max(total, 1):.1f}%), "
            f"{frames / seconds:,.0f} frames/s, ETA {eta}, last episode return {ret}")


def _hms(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def _next_multiple(step: int, every: int) -> Optional[int]:
    return None if not every else (step // every + 1) * every


def _step_counters(ckpt: dict, action_repeat: int) -> dict:
    """The loop's schedule counters in agent steps, from a checkpoint of any version.

    Checkpoints written before budgets counted agent steps hold frame counters; the next
    evaluation / checkpoint falls on the first agent step at or past the saved frame, as it did.
    """
    if "next_eval_step" in ckpt:
        return {k: ckpt[k] for k in ("next_eval_step", "next_ckpt_step", "last_eval_step")}
    ceil = lambda frame: None if frame is None else steps_for_frames(frame, action_repeat)  # noqa: E731
    last = ckpt["last_eval_frame"]
    return {"next_eval_step": ceil(ckpt["next_eval_frame"]), "next_ckpt_step": ceil(ckpt["next_ckpt_frame"]),
            "last_eval_step": -1 if last < 0 else last // action_repeat}


def _summary(rows: list[dict]) -> str:
    text = ", ".join(f"{r['mode']} {r['return_mean']:.1f} ± {r['return_std']:.1f}" for r in rows)
    return text if len(rows) > 1 else text.split(" ", 1)[1]


def _say(bar, text: str) -> None:
    if not bar.disable:
        bar.write(text)
    else:
        print(text, flush=True)
