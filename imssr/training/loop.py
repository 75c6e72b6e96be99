"""The training loop: seed phase, updates, evaluation, logging, checkpoints.

Counters (:class:`~imssr.training.state.RunState`): ``frame`` counts environment (simulator)
frames, ``step`` counts agent steps (``frame = step * action_repeat``).  The budget, evaluation
and checkpoint intervals and the beta schedule count agent steps, as the authors' code does;
every log carries both counters.
Checkpoints are taken at episode ends, where the next thing the loop does is a reset from the
saved task RNG, so ``--resume`` reproduces the uninterrupted run; a stop request, and a budget
that runs out inside an episode, checkpoint the open episode too
(:class:`~imssr.training.state.Episode`), which a resume steps through again.
"""
from __future__ import annotations

import math
import os
import signal
import threading
import time
from typing import Optional

import numpy as np
import torch

from imssr._gl import gl_renderer, software_rendering_warning
from imssr.config import RunConfig
from imssr.contention import contention_warning
from imssr.data import FOOTAGE_DIR_ENV, IMAGE_DIR_ENV
from imssr.envs import env_from_config
from imssr.errors import DIVERGED_PREFIX, INTERRUPTED_EXIT, DivergedError, ImssrError, NonFiniteError
from imssr.plots.curves import plot_learning_curve
from imssr.presets import get_algo
from imssr.replay import make_replay_buffer, replay_placement
from imssr.replay.buffer import ReplayFileError
from imssr.rng import rng_states, seed_everything, set_rng_states
from imssr.rundir import RunDir
from imssr.seeds import TRAINING_EVAL_SEED_OFFSET
from imssr.training.build import build_agent, resolve_device
from imssr.training.evaluate import eval_row, evaluate, non_finite_text
from imssr.training.logger import Logger
from imssr.training.progress import PROGRESS_EVERY_S, Progress, eval_summary
from imssr.training.state import Episode, RunState

# Settings that may change between a run and its resume.
RESUMABLE_CHANGES = {"train.steps", "train.device", "train.replay_device", "train.gpu_share", "train.progress",
                     "train.tensorboard", "agent.precision", "agent.tf32", "agent.compile",
                     "train.torch_threads", "train.eval_episodes", "train.eval_every_steps",
                     "train.checkpoint_every_steps", "train.eval_modes", "train.save_buffer",
                     "train.wandb", "train.wandb_project", "train.wandb_group", "train.eval_video_every",
                     "train.eval_video_format"}

# Training metrics in the order a divergence names them: the raw intrinsic signal (its mean), which
# enters the critic's target within the same update, then the critic's loss.
DIVERGENCE_ORDER = ("r_int_raw", "critic_loss", "actor_loss", "alpha_loss", "aux_loss", "rnd_loss", "q_mean",
                    "alpha", "entropy")


class TrainingInterrupted(Exception):
    """Training stopped on a signal after checkpointing its last agent step; the message is the
    line the CLI prints ("stopped at agent step N by SIGTERM; continue with: ...")."""


class StopRequest:
    """SIGTERM / SIGINT as a request to stop after the current agent step (SLURM sends SIGTERM
    on preemption and at the time limit, some seconds before SIGKILL).

    The first signal is recorded in :attr:`signal_name`; a second one stops at once.  With
    ``out_dir`` (the command line, which trains that run directory) the second signal ends the
    process there with :data:`~imssr.errors.INTERRUPTED_EXIT` and one line, even in the middle
    of a checkpoint write: the write is atomic, so the last checkpoint stays whole, and the line
    names ``--resume`` only when there is a checkpoint to continue from.  Without ``out_dir``
    (the Python API) the default handlers come back: SIGTERM kills the process, SIGINT raises
    ``KeyboardInterrupt``.  Handlers are installed only on the main thread (Python's rule)."""

    SIGNALS = (signal.SIGTERM, signal.SIGINT)

    def __init__(self, out_dir: Optional[str] = None):
        self.signal_name: Optional[str] = None
        self.out_dir = out_dir
        self._previous: dict = {}

    def install(self) -> "StopRequest":
        if threading.current_thread() is threading.main_thread():
            for signum in self.SIGNALS:
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def _handle(self, signum, frame) -> None:
        self.signal_name = signal.Signals(signum).name
        # os.write, not print: a signal handler may run inside a print to the same stream.
        _say(f"imssr: {self.signal_name}: stopping after this agent step with a checkpoint "
             "(a second signal stops at once)\n")
        for sig in self.SIGNALS:  # the next signal acts at once
            if self.out_dir is not None:
                signal.signal(sig, self._exit_at_once)
            else:
                signal.signal(sig, signal.default_int_handler if sig == signal.SIGINT else signal.SIG_DFL)

    def _exit_at_once(self, signum, frame) -> None:
        """The second signal on the command line: one line and the exit, with no exception that
        could surface in a write (torch's "unexpected pos"), a ``finally`` or an exit handler."""
        name = signal.Signals(signum).name
        if RunDir(self.out_dir).has_checkpoint():
            text = (f"stopped at once, keeping the last checkpoint; continue with: "
                    f"imssr train --out {self.out_dir} --resume")
        else:
            # The directory holds the logs of the run so far, so the same command is refused.
            text = (f"stopped at once, before the run's first checkpoint: nothing to resume; choose "
                    f"another --out or remove {self.out_dir}")
        _say(f"imssr: {name} again: {text}\n")
        os._exit(INTERRUPTED_EXIT)

    def uninstall(self) -> None:
        """The handlers from before :meth:`install` come back (the caller's, when ``imssr.cli.main``
        runs in a process of its own): the training, and any checkpoint write, is over."""
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()


def _say(text: str) -> None:
    """``text`` to stderr from a signal handler; lost when stderr is gone (a closed pipe): the
    stop goes on without its line."""
    try:
        os.write(2, text.encode())
    except OSError:
        pass


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

    The trainer holds an exclusive lock on ``out_dir`` (:mod:`imssr.rundir.lock`) from
    before it writes or deletes anything there until :meth:`close`.
    """

    def __init__(self, cfg: RunConfig, out_dir: str, resume: bool = False, refill_buffer: bool = False,
                 stop: Optional[StopRequest] = None):
        if os.path.exists(out_dir) and not os.path.isdir(out_dir):
            raise ImssrError(f"--out {out_dir} is a file, not a directory")
        # A second process on the same directory fails here, before anything is checked or written.
        self.run_dir = RunDir(out_dir)
        self._lock = self.run_dir.open()
        self.refill_buffer = refill_buffer
        self.stop = stop or StopRequest()  # uninstalled: never set
        self._resume_episode: Optional[dict] = None  # the episode a stop left open, to rebuild
        self._resume_burst: Optional[dict] = None  # the burst a stop left unfinished, to go on with
        # The evaluation state from before the off-schedule evaluation at the end of the budget:
        # a checkpoint holds it so that a larger budget goes on as if that evaluation never ran.
        self._before_final: Optional[dict] = None
        self._saved_step = -1  # the agent step of this process's last checkpoint
        self._replay_file: Optional[str] = None  # the replay file that latest.pt names
        self.resumed_from: Optional[str] = None
        self._fallback = False
        try:
            self._setup(cfg, out_dir, resume)
        except BaseException:
            self.close()
            raise

    def _setup(self, cfg: RunConfig, out_dir: str, resume: bool) -> None:
        """Check the config and the run directory, build the envs, agent and replay buffer,
        restore a resumed run's checkpoint, write config.json and open the logs."""
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
                                                 cfg.train.replay_capacity * 3 * cfg.env.image_size ** 2,
                                                 cfg.train.gpu_share)
        ckpt = None
        if resume:
            ckpt = self._check_resume()
            if ckpt["step"] > cfg.train.steps:
                # Refused before anything (config.json) is rewritten with the smaller budget.
                raise ImssrError(f"the run in {out_dir} is already at agent step {ckpt['step']:,}, past the "
                                 f"budget of {cfg.train.steps:,} steps asked for; resume with --steps "
                                 f"{ckpt['step']} or more")
        else:
            self.run_dir.refuse_fresh_start()
        self._set_threads(ckpt)
        seed_everything(cfg.train.seed)
        e = cfg.env
        # Training footage and evaluation footage come from disjoint pools.
        self.env = env_from_config(e, seed=cfg.train.seed, footage_split="train")
        self.eval_modes = cfg.train.eval_mode_list(e.mode)
        self.eval_envs = {m: env_from_config(e, seed=cfg.train.seed + TRAINING_EVAL_SEED_OFFSET, mode=m,
                                             footage_split="test")
                          for m in self.eval_modes}
        self._warn_on_software_rendering()
        self._build_agent_and_replay()
        os.makedirs(out_dir, exist_ok=True)
        if ckpt is not None:
            self._restore(ckpt)
        self.run_dir.write_config(cfg)
        self.logger = self._open_logger(resumed=ckpt is not None)
        if ckpt is not None:
            # The checkpoint's evaluation history is authoritative for eval logs.
            self.logger.rewrite_eval(self.state.eval_history)
            print(f"imssr: resuming from agent step {self.step:,} (frame {self.frame:,}) of "
                  f"{cfg.train.steps:,}", flush=True)
        warning = no_update_warning(self.state.learning_starts, cfg.total_steps)
        if warning:
            print(warning, flush=True)

    def _set_threads(self, ckpt: Optional[dict]) -> None:
        """Apply ``train.torch_threads``; warn when the threads would contend with busy cores, and
        when a CPU run resumes with another thread count than checkpoint ``ckpt`` was saved with."""
        if self.cfg.train.torch_threads:
            torch.set_num_threads(self.cfg.train.torch_threads)
        warning = contention_warning(torch.get_num_threads())
        if warning:
            print(warning, flush=True)
        if ckpt is not None:
            warning = thread_warning(ckpt.get("torch_threads"), torch.get_num_threads(), self.device)
            if warning:
                print(warning, flush=True)

    def _warn_on_software_rendering(self) -> None:
        """On a GPU machine, warn when MuJoCo's EGL renders on the CPU (llvmpipe)."""
        if torch.cuda.is_available():
            warning = software_rendering_warning(os.environ.get("MUJOCO_GL", "egl"),
                                                 gl_renderer(self.env.physics), gpu=True)
            if warning:
                print(warning, flush=True)

    def _build_agent_and_replay(self) -> None:
        """The agent, the replay buffer and the loop's state at agent step 0, in the order
        their random draws have always had (weights, SODA's image pool, then the streams spawned
        from the seed)."""
        cfg, e = self.cfg, self.cfg.env
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
        t = cfg.train
        self.state = RunState.fresh(t.eval_every_steps, t.checkpoint_every_steps, t.seed_steps, action_seq)

    def _open_logger(self, resumed: bool) -> Logger:
        """The run's logs (CSV, TensorBoard, W&B); a resumed run's are cut back to its checkpoint."""
        cfg, out_dir = self.cfg, self.out_dir
        wandb = None
        if cfg.train.wandb:
            # Imported here: W&B is an extra, and a run without it must not load it.
            from imssr.training.wandb_run import WandbRun

            wandb = WandbRun(cfg, out_dir, resume=resumed, warn=lambda text: print(text, flush=True))
        return Logger(out_dir, cfg.train.tensorboard, resume_frame=self.frame if resumed else None, wandb=wandb)

    @property
    def step(self) -> int:
        """The agent step the run is at (:attr:`state` holds it)."""
        return self.state.step

    @property
    def frame(self) -> int:
        """The environment frame the run is at (:attr:`state` holds it)."""
        return self.state.frame

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
        """Continue from checkpoint ``ckpt``: the agent, the loop's state, every generator, the
        replay buffer (or a refill when there is none) and the episode a stop left open."""
        try:
            self.agent.load_state_dict(ckpt["agent"])
        except (RuntimeError, KeyError, ValueError) as exc:
            raise ImssrError(f"checkpoint does not match this agent: {str(exc).splitlines()[0]}") from None
        counters = _step_counters(ckpt)
        saved_train = RunConfig.from_dict(ckpt["config"]).train
        # Intervals may change on resume: keep the saved schedule only when they did not.
        self.state.load(ckpt, counters, saved_train.eval_every_steps, saved_train.checkpoint_every_steps)
        self.env.set_rng_state(ckpt["env_rng"])
        saved = ckpt.get("eval_env_rngs") or {self.cfg.env.mode: ckpt.get("eval_env_rng")}
        for mode, env in self.eval_envs.items():
            if saved.get(mode) is not None:  # a scene added on resume starts from its seed
                env.set_rng_state(saved[mode])
        set_rng_states(ckpt["global_rng"])
        self._restore_before_final(ckpt.get("before_final_eval"))
        refill = self._load_replay(ckpt)
        if ckpt.get("episode_state") is not None and not refill:
            # Stopped (or out of budget) mid-episode: train() rebuilds the open episode first.
            self._resume_episode = ckpt["episode_state"]
            self._resume_burst = ckpt.get("burst_state")
        if not self._fallback:
            self._saved_step = self.step  # latest.pt holds this step already
        if refill:
            self.state.learning_starts = self.step + max(self.cfg.train.seed_steps, self.cfg.agent.batch_size)
            print(f"imssr: warning: {refill}; refilling it with random "
                  f"actions until agent step {self.state.learning_starts} (the resume is not exact)", flush=True)

    def _restore_before_final(self, before: Optional[dict]) -> None:
        """A checkpoint taken where the budget ran out after an evaluation off the schedule (the
        final one): with a larger budget now, the run goes on as if that evaluation never ran
        (its rows dropped, the evaluation envs' generators as before it), as a run given the
        larger budget from the start does; with the same budget it is kept for a later one."""
        if before is None:
            return
        if self.cfg.total_steps <= self.step:
            self._before_final = before
            return
        s = self.state
        del s.eval_history[before["evaluations"]:]
        s.last_eval_step = before["last_eval_step"]
        for mode, env in self.eval_envs.items():
            if mode in before["eval_env_rngs"]:
                env.set_rng_state(before["eval_env_rngs"][mode])

    def _load_replay(self, ckpt: dict) -> Optional[str]:
        """Load the replay buffer checkpoint ``ckpt`` names; returns why it must be refilled
        instead (None when it loaded)."""
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
        return refill

    def save(self, episode: Optional[Episode] = None, burst: Optional[dict] = None) -> None:
        """Checkpoint now (``episode``: the open episode, when stopping in its middle; ``burst``:
        the burst of updates a stop interrupted, :meth:`_stop_in_burst`).  A save that fails (a
        full disk) leaves the previous checkpoint as it was and removes the replay files it
        wrote, which no checkpoint names."""
        latest = self.run_dir.latest
        before = _identity(latest)
        try:
            self._save(episode, burst)
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

    def _rebuild_episode(self, state: dict) -> tuple[Episode, np.ndarray]:
        """Step the env through the open episode a checkpoint saved (``episode_state``); returns
        the episode and its current observation."""
        episode = Episode.from_state_dict(state)
        saved_rng = self.env.get_rng_state()
        self.env.set_rng_state(episode.env_rng)
        obs, _ = self.env.reset()
        for action in episode.actions:
            obs, *_ = self.env.step(action)
        if self.env.get_rng_state() != saved_rng:
            raise ImssrError(f"cannot rebuild the episode open in {self.resumed_from}: the environment's "
                             "random state differs from the saved one")
        return episode, obs

    def _save(self, episode: Optional[Episode] = None, burst: Optional[dict] = None) -> None:
        replay_file = None
        if self.cfg.train.save_buffer:
            replay_file = self.run_dir.replay_name(self.step)
            self.replay.save(self.run_dir.replay_path(replay_file))
        state = {
            "config": self.cfg.to_dict(), **self.state.state_dict(), "agent": self.agent.state_dict(),
            "env_rng": self.env.get_rng_state(), "eval_env_rngs": {m: env.get_rng_state() for m, env in self.eval_envs.items()},
            "global_rng": rng_states(),
            "replay_file": replay_file, "replay_state": self.replay.state_dict(),
            # A resume with another thread count is valid but not bit-identical (thread_warning).
            "torch_threads": torch.get_num_threads(),
            "episode_state": None if episode is None else episode.state_dict(self.action_dim),
            "burst_state": burst, "before_final_eval": self._before_final,
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
        t, s = self.cfg.train, self.state
        # This evaluation's number, counted from the history so that a resume keeps the rhythm.
        number = len({item["row"]["step"] for item in s.eval_history}) + 1
        record = t.eval_video_every > 0 and number % t.eval_video_every == 0
        rows = []
        for mode, env in self.eval_envs.items():
            frames: Optional[list] = [] if record else None
            returns = evaluate(self.agent, env, t.eval_episodes, record=frames)
            row = dict(eval_row(s.frame, s.step, mode, returns), wall_time=time.time())
            self.logger.log_eval(row, returns)
            if frames:
                self.logger.log_video(mode, frames, s.frame, s.step, t.eval_video_format)
            s.eval_history.append({"row": row, "returns": returns})
            rows.append(row)
        s.last_eval_step = s.step
        return rows

    progress_every_s: float = PROGRESS_EVERY_S
    """Seconds between progress lines when stdout is not a terminal (see :data:`PROGRESS_EVERY_S`)."""

    def train(self) -> None:
        """Train to ``cfg.train.steps`` agent steps: act, learn, step the env; evaluate and
        checkpoint when due; log each episode at its end.  A stop request (:attr:`stop`)
        checkpoints after the current agent step and raises :class:`TrainingInterrupted`.

        A NaN or infinite action (checked on the host before the simulator sees it), training
        metric (checked once per episode, with the episode's metrics) or intrinsic signal stops
        the run with :class:`DivergedError` ("diverged at agent step N: critic loss nan"); the
        last checkpoint is from before it, since nothing is saved after a divergence.
        """
        cfg, s, total = self.cfg, self.state, self.cfg.total_steps
        progress = Progress(total, s.step, s.frame, f"{cfg.algo} {cfg.env.task} s{cfg.train.seed}",
                            bar=cfg.train.progress, every_s=self.progress_every_s,
                            learning_starts=s.learning_starts)
        episode, obs = self._reopen_episode()
        try:
            while s.step < total:
                if episode is None:
                    episode, obs = self._start_episode()
                action = self._act(obs, episode)
                obs, episode_over = self._env_step(action, episode)
                progress.step(s.step, s.frame, s.last_return)
                self._evaluate_if_due(progress)
                if episode_over:
                    self._end_episode(episode, progress)
                    episode = None
                    self._final_evaluation_if_last(progress)
                    self._checkpoint_if_due()
                self._stop_if_requested(episode)
            self._finish(episode)
        except NonFiniteError as exc:
            raise DivergedError(f"{DIVERGED_PREFIX} {s.step}: {self._divergence(exc, episode)}") from None
        finally:
            progress.close()
            self.logger.close()

    # The loop's steps, in the order it takes them.
    def _reopen_episode(self) -> tuple[Optional[Episode], Optional[np.ndarray]]:
        """The episode a stop left open and its observation, rebuilt (None, None: none)."""
        if self._resume_episode is None:
            return None, None
        state, self._resume_episode = self._resume_episode, None
        return self._rebuild_episode(state)

    def _start_episode(self) -> tuple[Episode, np.ndarray]:
        """Reset the training env (remembering its RNG state for a rebuild) and store the first
        frame; returns the new episode and its first observation."""
        episode = Episode(env_rng=self.env.get_rng_state())
        obs, info = self.env.reset()
        self.replay.add_first(info["frame"], self.env.physics_state(), self.state.step)
        return episode, obs

    def _act(self, obs: np.ndarray, episode: Episode) -> np.ndarray:
        """This agent step's action: uniform random until ``learning_starts``, else the policy's
        sample, after which the agent learns (:meth:`_learn`)."""
        s = self.state
        if s.step < s.learning_starts:
            return s.action_rng.uniform(-1.0, 1.0, self.action_dim).astype(np.float32)
        if self._resume_burst is not None:
            # Stopped inside the burst: its action was drawn before the stop; the updates go on.
            burst, self._resume_burst = self._resume_burst, None
            action = burst["action"].numpy()
            self._learn(episode, action, done=int(burst["updates_done"]))
            return action
        action = self.agent.act(obs, deterministic=False)
        if not np.isfinite(action).all():  # a few host values: no device sync
            raise DivergedError(f"action {non_finite_text(action)}")
        self._learn(episode, action)
        return action

    def _learn(self, episode: Episode, action: np.ndarray, done: int = 0) -> None:
        """One update, or the burst of ``train.burst_updates`` once, when the first seed phase
        ends (not after a refill), from its update ``done`` on; the episode sums their metrics.
        A stop request inside the burst does not wait for its end (:meth:`_stop_in_burst`)."""
        t, step = self.cfg.train, self.state.step
        updates = max(1, t.burst_updates) if step == t.seed_steps else 1
        for update in range(done, updates):
            if update > done and self.stop.signal_name is not None:
                self._stop_in_burst(episode, action, update)
            episode.add_metrics(self.agent.update(self.replay, step))

    def _env_step(self, action: np.ndarray, episode: Episode) -> tuple[np.ndarray, bool]:
        """Step the training env, store the transition and count the agent step; returns the
        next observation and whether the episode is over."""
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.replay.add(action, reward, 0.0 if terminated else 1.0, info["frame"],
                        self.env.physics_state(), self.state.step + 1)
        self.state.step += 1
        self.state.frame += info["sim_steps"]
        episode.add_step(action, reward, info["sim_steps"])
        return obs, terminated or truncated

    def _evaluate_if_due(self, progress: Progress) -> None:
        """The periodic evaluation, at the first agent step at or past the schedule's next."""
        s = self.state
        if s.eval_schedule.due(s.step):
            rows = self.run_eval()
            s.eval_schedule.advance(s.step)
            progress.say(f"eval step {s.step} frame {s.frame}: return " + eval_summary(rows))

    def _end_episode(self, episode: Episode, progress: Progress) -> None:
        """Log the finished episode's ``train.csv`` row, unless a metric diverged (then raise)."""
        s = self.state
        row = episode.train_row(s.frame, s.step, s.episode)
        bad = first_non_finite(row, episode.sums, self._metric_names())
        if bad:
            raise DivergedError(bad)
        self.logger.log_train(row)
        s.last_return = episode.total_reward
        progress.episode_end(episode.total_reward, row["fps"], s.frame)
        s.episode += 1

    def _final_evaluation_if_last(self, progress: Progress) -> None:
        """At the episode end that spends the budget: the final evaluation, unless this agent
        step was just evaluated."""
        s = self.state
        if s.step >= self.cfg.total_steps and s.last_eval_step != s.step:
            rows = self._final_evaluation()
            progress.say(f"final eval step {s.step} frame {s.frame}: return " + eval_summary(rows))

    def _final_evaluation(self) -> list[dict]:
        """The evaluation where the budget runs out, off the schedule (:meth:`run_eval`); what it
        is about to change is kept for the checkpoint (:meth:`_restore_before_final`)."""
        s = self.state
        self._before_final = {"eval_env_rngs": {m: env.get_rng_state() for m, env in self.eval_envs.items()},
                              "evaluations": len(s.eval_history), "last_eval_step": s.last_eval_step}
        return self.run_eval()

    def _checkpoint_if_due(self) -> None:
        """At an episode end: a checkpoint when the schedule says so, and at the last one."""
        s = self.state
        if s.step >= self.cfg.total_steps or s.ckpt_schedule.due(s.step):
            s.ckpt_schedule.advance(s.step)
            self.save()

    def _stop_if_requested(self, episode: Optional[Episode]) -> None:
        """On a stop request before the budget is spent: a checkpoint of this agent step (with
        the open ``episode``, if any) unless an episode end just wrote one, then
        :class:`TrainingInterrupted`."""
        if self.stop.signal_name is None or self.step >= self.cfg.total_steps:
            return
        if self._saved_step != self.step:
            self._raise_if_diverged(episode)
            self.save(episode)
        raise self._interrupted()

    def _stop_in_burst(self, episode: Episode, action: np.ndarray, done: int) -> None:
        """On a stop request inside the burst of updates, after ``done`` of them: a checkpoint
        of where it is (the open ``episode``, the step's ``action``, drawn before the burst, and
        the count), from which a resume does the rest of the burst and then takes the action,
        then :class:`TrainingInterrupted`."""
        self._raise_if_diverged(episode)
        self.save(episode, burst={"updates_done": done, "action": torch.from_numpy(action.astype(np.float32))})
        raise self._interrupted()

    def _interrupted(self) -> TrainingInterrupted:
        return TrainingInterrupted(f"stopped at agent step {self.step} by {self.stop.signal_name}; "
                                   f"continue with: imssr train --out {self.out_dir} --resume")

    def _finish(self, episode: Optional[Episode]) -> None:
        """The budget is spent: when it ended mid-episode, evaluate (unless this agent step was)
        and checkpoint with the open episode, which a larger budget continues exactly (unless
        this step is checkpointed already and the evaluation did not just change it: a run
        stopped here and resumed to this budget evaluates now); the learning curve goes to W&B."""
        if episode is not None:
            self._raise_if_diverged(episode)
            evaluated = self.state.last_eval_step != self.step
            if evaluated:
                self._final_evaluation()
            if evaluated or self._saved_step != self.step:
                self.save(episode)
        if self.logger.wants_media:
            self.logger.log_image("learning_curve", plot_learning_curve(self.out_dir), self.frame, self.step)

    def _raise_if_diverged(self, episode: Optional[Episode]) -> None:
        """Before a checkpoint in the middle of ``episode``: its metrics so far, which are
        otherwise checked only at its end, so that no checkpoint holds an agent whose update
        diverged (one host sync per such checkpoint)."""
        bad = self._first_non_finite_metric(episode)
        if bad:
            raise DivergedError(bad)

    def _first_non_finite_metric(self, episode: Optional[Episode]) -> Optional[str]:
        """``"critic loss nan"`` for the open ``episode``'s first non-finite training metric so
        far (one host sync), None when all are finite or there is no episode."""
        sums = {} if episode is None else episode.sums
        return first_non_finite({k: float(v) for k, v in sums.items()}, sums, self._metric_names())

    def _divergence(self, exc: NonFiniteError, episode: Optional[Episode]) -> str:
        """What diverged: the first non-finite training metric of the open ``episode`` (one host
        sync, only now), else what ``exc`` found (the action, the intrinsic signal)."""
        return self._first_non_finite_metric(episode) or str(exc)

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


def no_update_warning(learning_starts: int, total: int) -> Optional[str]:
    """A one-line warning when the agent would never be updated: its seed phase of random actions
    (``train.seed_steps``; after a refill, until ``learning_starts``) lasts the whole budget of
    ``total`` agent steps.  A warning, not an error: a random policy's returns are a baseline."""
    if learning_starts < total:
        return None
    return (f"imssr: warning: the seed phase (--seed-steps) acts at random until agent step {learning_starts:,} "
            f"and the budget (--steps) ends at {total:,}: the agent is never updated")


def first_non_finite(values: dict, keys, names: Optional[dict[str, str]] = None) -> Optional[str]:
    """``"critic loss nan"`` for the first of ``keys`` (in :data:`DIVERGENCE_ORDER`, then the
    rest) whose value in ``values`` is NaN or infinite, named as in ``names`` or by its key;
    None when all are finite."""
    ordered = [k for k in DIVERGENCE_ORDER if k in keys] + sorted(k for k in keys if k not in DIVERGENCE_ORDER)
    for k in ordered:
        v = values.get(k)
        if isinstance(v, float) and not math.isfinite(v):
            return f"{(names or {}).get(k, k.replace('_', ' '))} {v}"
    return None


def _step_counters(ckpt: dict) -> dict:
    """The loop's schedule counters, in agent steps, from a checkpoint."""
    return {k: ckpt[k] for k in ("next_eval_step", "next_ckpt_step", "last_eval_step")}
