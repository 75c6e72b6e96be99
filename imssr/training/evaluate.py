"""Evaluation: deterministic policy (tanh of the mean), centre crop, K episodes; and the
evaluation of a saved run (``imssr evaluate``)."""
from __future__ import annotations

import functools
import os
import tempfile
import time
from typing import Callable, Optional

import numpy as np

from imssr.envs import env_from_config
from imssr.envs.worker import step_all
from imssr.envs.scenes import get_mode
from imssr.errors import DivergedError, ImssrError
from imssr.files import open_own
from imssr.plots.media import save_montage, save_video
from imssr.rundir import RunDir, as_run_dir
from imssr.seeds import evaluation_seed
from imssr.training.build import agent_at, resolve_device
from imssr.training.logger import EVAL_COLUMNS, EVAL_EPISODE_COLUMNS, Logger, append_locked, episode_rows
from imssr.training.progress import advance, phase
from imssr.training.state import RunState


def evaluate(agent, env, episodes: int, record: Optional[list] = None) -> list[float]:
    """Undiscounted returns of ``episodes`` episodes of ``env``.

    With ``record`` (a list), the first episode's frames (``(H, W, 3)`` uint8,
    what the agent sees) are appended to it.
    """
    ((returns, frames, error),) = evaluate_members(
        lambda obs: {k: agent.act(o, deterministic=True) for k, o in obs.items()}, [env], episodes, record is not None)
    if record is not None:
        record.extend(frames)
    if error is not None:
        raise error
    return returns


def evaluate_members(act, envs: list, episodes: int, record: bool = False) -> list[list]:
    """:func:`evaluate` of several agents at once, each in its own env (``envs[k]``), their
    episodes in lockstep: ``act(observations)`` gives every agent's deterministic action for its
    observation in one call (a batch of agents' members).  Returns, per env, its returns, the
    first episode's frames when ``record``, and the error that stopped it (a non-finite action),
    as :func:`evaluate` would have raised it (the simulator would end in a PhysicsError traceback;
    the trainer adds the step); an env that ended its episode waits for the others."""
    results = [[[], [], None] for _ in envs]
    for episode in range(episodes):
        live = [k for k, r in enumerate(results) if r[2] is None]
        obs, totals, done = {}, {k: 0.0 for k in live}, set()
        for k in live:
            obs[k], info = envs[k].reset()
            if record and episode == 0:
                results[k][1].append(_hwc(info["frame"]))
        while len(done) < len(live):
            actions = act(obs)
            for k in live:
                if k not in done and not np.isfinite(actions[k]).all():
                    results[k][2] = DivergedError(f"evaluation action {non_finite_text(actions[k])}")
                    done.add(k)
            stepping = [k for k in live if k not in done]
            for k, step in zip(stepping, step_all([envs[k] for k in stepping], [actions[k] for k in stepping])):
                obs[k], reward, terminated, truncated, info = step
                if record and episode == 0:
                    results[k][1].append(_hwc(info["frame"]))
                totals[k] += reward
                if terminated or truncated:
                    done.add(k)
        for k in live:
            if results[k][2] is None:
                results[k][0].append(float(np.asarray(totals[k])))
        advance()  # the phase that shows this evaluation's progress, if one is open
    return results


def non_finite_text(values) -> str:
    """The first non-finite value of ``values`` as text: ``nan``, ``inf`` or ``-inf``."""
    values = np.asarray(values, dtype=np.float64).ravel()
    bad = values[~np.isfinite(values)]
    return str(float(bad[0])) if bad.size else "finite"


def _hwc(frame: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.moveaxis(frame, 0, -1))


def eval_row(frame: int, step: int, mode: str, returns: list[float]) -> dict:
    """The ``eval.csv`` summary of one evaluation."""
    return {"frame": frame, "step": step, "mode": mode,
            "return_mean": float(np.mean(returns)), "return_std": float(np.std(returns)),
            "episodes": len(returns), "return_min": float(np.min(returns)),
            "return_max": float(np.max(returns))}


def evaluate_in_training(agent, eval_envs: dict, t, state: RunState, logger: Logger,
                         episodes_of: Callable = evaluate) -> list[dict]:
    """The evaluation of a training at ``state``'s step in every scene of ``eval_envs`` (``t``: the
    run's ``train`` config): ``t.eval_episodes`` episodes each, one ``eval.csv`` row each, kept in
    ``state.eval_history``.  At every ``t.eval_video_every``-th evaluation, the first episode of
    each scene is recorded (the frames the evaluation renders anyway: the returns do not change).
    ``episodes_of``: :func:`evaluate`, or what stands in for it (a batch of runs' lockstep
    evaluation, :mod:`imssr.training.seeds`)."""
    # This evaluation's number, counted from the history so that a resume keeps the rhythm.
    number = len({item["row"]["step"] for item in state.eval_history}) + 1
    record = t.eval_video_every > 0 and number % t.eval_video_every == 0
    rows = []
    for mode, env in eval_envs.items():
        frames: Optional[list] = [] if record else None
        returns = episodes_of(agent, env, t.eval_episodes, record=frames)
        row = dict(eval_row(state.frame, state.step, mode, returns), wall_time=time.time())
        logger.log_eval(row, returns)
        if frames:
            logger.log_video(mode, frames, state.frame, state.step, t.eval_video_format)
        state.eval_history.append({"row": row, "returns": returns})
        rows.append(row)
    state.last_eval_step = state.step
    return rows


def evaluate_run(run_dir: RunDir | str, checkpoint: Optional[str] = None, episodes: int = 10,
                 modes: Optional[str] = None, seed: Optional[int] = None, device: str = "cpu",
                 video: Optional[str] = None, montage: bool = False, footage: Optional[str] = None,
                 log: Optional[Callable[[str], None]] = None, progress: bool = True) -> None:
    """Evaluate a saved run's checkpoint in each scene; append the results to
    ``RUN/evaluate.csv`` (one row per scene) and ``RUN/evaluate_episodes.csv`` (one per episode).

    Args:
        run_dir: the run directory (its ``config.json`` and checkpoints): its path or its
            :class:`~imssr.rundir.RunDir`.
        checkpoint: a checkpoint file, or the agent step of a retained ``step-*.pt``; None: the
            latest that verifies.
        episodes: episodes per scene.
        modes: comma-separated scenes; None: the run's evaluation scenes.
        seed: seed of the evaluation envs; None: the run seed + 20,000 (no env of training or of
            its evaluations used it).
        device: torch device name (``auto`` allowed).
        video: ``gif`` or ``mp4``: save each scene's first episode as ``RUN/videos/MODE.EXT``.
        montage: save ``RUN/montage.png``, one frame per scene.
        footage: footage for video scenes; None: the run's.
        log: where the result lines go (default: stdout, flushed).
        progress: show each scene's episodes as they run (a bar on a terminal, else a line
            every minute: :func:`~imssr.training.progress.phase`).
    """
    log = log or functools.partial(print, flush=True)
    run = as_run_dir(run_dir).require()
    cfg = run.read_config()
    scenes = [m.strip() for m in modes.split(",") if m.strip()] if modes else cfg.train.eval_mode_list(cfg.env.mode)
    for mode in scenes:
        get_mode(mode)
    ckpt, _, note = run.checkpoint(checkpoint, verb="evaluating")
    if note:
        log(f"imssr: {note}")
    resolve_device(device)  # a bad device fails before any env is built
    _check_writable(run, video=bool(video), montage=montage)
    seed = evaluation_seed(cfg.train.seed) if seed is None else seed
    agent = None
    pictures, rows, episodes_rows = {}, [], []
    for mode in dict.fromkeys(scenes):
        # Unseen footage: evaluation draws from the test pool.
        env = env_from_config(cfg.env, seed=seed, mode=mode, footage_split="test", footage_path=footage)
        frames: Optional[list] = [] if (video or montage) else None
        try:
            if agent is None:
                agent = agent_at(ckpt, cfg, device=device, env=env).agent
            with phase(f"evaluating in {mode}", episodes, "episodes", show=progress):
                returns = evaluate(agent, env, episodes, record=frames)
        finally:
            env.close()
        row = eval_row(ckpt.frame, ckpt.step, mode, returns)
        rows.append(row)
        episodes_rows += episode_rows(row, returns)
        log(f"{mode}: return {row['return_mean']:.1f} ± {row['return_std']:.1f} over {len(returns)} "
            f"episode{'' if len(returns) == 1 else 's'} (checkpoint at frame {ckpt.frame}, step {ckpt.step})")
        if video:
            log(f"  video: {save_video(frames, run.video_path(f'{mode}.{video}'))}")
        if montage:
            pictures[mode] = frames[min(len(frames) - 1, 20)]
    if pictures:
        path = save_montage(pictures, run.montage_path, f"{cfg.algo} on {cfg.env.task}, frame {ckpt.frame}")
        log(f"montage: {path}")
    # Appended to, one summary row per scene and one row per episode (with the checkpoint's step),
    # each file in one locked append: two evaluations of the run at once never interleave.
    append_locked(run.evaluate_episodes_log, EVAL_EPISODE_COLUMNS, episodes_rows)
    append_locked(run.evaluate_log, EVAL_COLUMNS, rows)
    log(f"imssr: evaluation written to {run.evaluate_log} and {run.evaluate_episodes_log}")


def _check_writable(run: RunDir, video: bool, montage: bool) -> None:
    """A one-line error, before any episode is played, when the evaluation could not write its
    results into ``run`` (a read-only file system or folder, a log that is not the user's): an
    evaluation takes minutes, and its returns would be lost.  The logs that exist are opened to
    append, changing nothing; a file to create needs its folder writable."""
    logs = (run.evaluate_log, run.evaluate_episodes_log)
    folders = {run.path for made in (montage, not all(os.path.lexists(p) for p in logs)) if made}
    if video:  # its folder is made in the run when missing
        folders.add(run.videos_dir if os.path.isdir(run.videos_dir) else run.path)
    try:
        for where in logs:
            if os.path.lexists(where):
                os.close(open_own(where, os.O_WRONLY | os.O_APPEND))
        for where in sorted(folders):
            with tempfile.TemporaryFile(dir=where):
                pass
    except OSError as exc:
        raise ImssrError(f"imssr evaluate cannot write its results to {where} ({exc.strerror or exc}): nothing was "
                         "evaluated; evaluate a copy of the run in a folder you can write") from None
