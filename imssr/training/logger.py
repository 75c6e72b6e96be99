"""CSV logs (always), TensorBoard and Weights & Biases (optional), all resumable; evaluation
videos and the learning curve as media.

Every row carries ``frame`` (environment frames) and ``step`` (agent steps).
On resume, rows newer than the checkpoint are dropped so that a killed run
continued from its checkpoint leaves the same files as an uninterrupted one.
"""
from __future__ import annotations

import csv
import fcntl
import math
import os
import threading
from typing import Any, Callable, Iterable, Optional

import numpy as np

from imssr.errors import ImssrError
from imssr.files import atomic_write_text, disk_full_as_error, is_disk_full, open_append, read_csv
from imssr.plots.media import save_video
from imssr.rundir import RunDir

VIDEO_FPS = 25.0
"""Frames per second of evaluation videos (one frame per agent step), as ``imssr evaluate --video``."""

TRAIN_COLUMNS = ["frame", "step", "episode", "episode_return", "episode_frames", "fps", "critic_loss", "actor_loss",
                 "alpha_loss", "alpha", "entropy", "q_mean", "aux_loss", "rnd_loss", "r_int_raw", "r_int_raw_std",
                 "r_int_mean", "r_int_std", "bonus_std", "beta", "updates", "wall_time"]
EVAL_COLUMNS = ["frame", "step", "mode", "return_mean", "return_std", "episodes",
                "return_min", "return_max", "wall_time"]
EVAL_EPISODE_COLUMNS = ["frame", "step", "mode", "episode", "return"]


class CSVLog:
    """Append-only CSV file with a fixed header; values are written as given."""

    def __init__(self, path: str, columns: list[str]):
        self.path, self.columns = path, columns
        if not os.path.exists(path):
            atomic_write_text(path, ",".join(columns) + "\n")

    def write(self, row: dict) -> None:
        # A line cut short by a full disk is dropped on resume (truncate_after).
        with disk_full_as_error(self.path), open_append(self.path, newline="") as fh:
            # Lines end in "\n", as the header and a resume's rewrite do (csv's default is "\r\n").
            csv.DictWriter(fh, self.columns, extrasaction="ignore", lineterminator="\n").writerow(
                {k: _fmt(row.get(k)) for k in self.columns})
            fh.flush()

    def truncate_after(self, frame: int) -> None:
        """Keep only rows with ``frame <= frame`` (used on resume)."""
        rows = read_csv(self.path)
        # A process killed mid-write can leave a partial last line: drop it.
        complete = [r for r in rows if None not in r.values() and None not in r and _is_number(r.get("frame"))]
        kept = [r for r in complete if int(float(r["frame"])) <= frame]
        lines = [",".join(self.columns)] + [",".join(_quote(r.get(c, "")) for c in self.columns) for r in kept]
        atomic_write_text(self.path, "\n".join(lines) + "\n")


def _fmt(v) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    if isinstance(v, float):
        return f"{v:.3f}" if abs(v) >= 1e5 else f"{v:.6g}"
    return str(v)


def _is_number(v) -> bool:
    try:
        float(v)
        return True
    except (TypeError, ValueError):
        return False


def _quote(v: str) -> str:
    return f'"{v}"' if ("," in v or '"' in v) else v


def episode_rows(row: dict, returns: Iterable[float]) -> list[dict]:
    """The per-episode rows of the evaluation summarised by ``row``."""
    return [{"frame": row["frame"], "step": row["step"], "mode": row["mode"], "episode": i, "return": ret}
            for i, ret in enumerate(returns)]


def _series(row: dict) -> dict[str, float]:
    """The TensorBoard and W&B scalars of a ``train.csv`` or ``eval.csv`` row, as logged or as read
    back from its file: ``train/<column>`` or ``eval/<mode>/<column>``, its counters left out."""
    prefix = f"eval/{row['mode']}" if "mode" in row else "train"
    return {f"{prefix}/{k}": float(v) for k, v in row.items()
            if k not in ("frame", "step", "episode", "mode", "episodes") and _is_number(v)}


def append_locked(path: str, columns: list[str], rows: list[dict]) -> None:
    """Append ``rows`` to a CSV file that several processes may append to at once (two ``imssr
    evaluate`` of one run): under an exclusive ``flock`` of the file, so the rows of one call stay
    together, with the header first when the file is new."""
    with disk_full_as_error(path), open_append(path, newline="") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)  # released when the file closes
        _drop_torn_line(path)
        if fh.seek(0, os.SEEK_END) == 0:
            fh.write(",".join(columns) + "\n")
        writer = csv.DictWriter(fh, columns, extrasaction="ignore", lineterminator="\n")
        writer.writerows({k: _fmt(r.get(k)) for k in columns} for r in rows)
        fh.flush()


def _drop_torn_line(path: str) -> None:
    """Cut a last line without its newline (a row that a full disk or a kill cut short) off the
    file, so that the next row starts on a line of its own instead of continuing the torn one.
    The file is read whole: ``imssr evaluate`` appends a few rows per call to it."""
    with open(path, "rb") as fh:
        text = fh.read()
    if text and not text.endswith(b"\n"):
        os.truncate(path, text.rfind(b"\n") + 1)


class Logger:
    """``train.csv``, ``eval.csv``, ``eval_episodes.csv``, TensorBoard and W&B of the run ``run``.

    ``wandb`` is the run's :class:`imssr.training.wandb_run.WandbRun` (None: no W&B); the logger
    finishes it on :meth:`close`.
    """

    def __init__(self, run: RunDir, tensorboard: bool = True, resume_frame: Optional[int] = None, wandb=None):
        self.run, self.wandb = run, wandb
        if resume_frame is None:
            # A fresh run starts only where no log holds a row (RunDir.refuse_fresh_start): the
            # header-only logs of a training stopped before its first row get this run's header.
            for path in run.training_logs:
                if os.path.exists(path):
                    os.unlink(path)
        self.train = CSVLog(run.train_log, TRAIN_COLUMNS)
        self.eval = CSVLog(run.eval_log, EVAL_COLUMNS)
        self.eval_episodes = CSVLog(run.eval_episodes_log, EVAL_EPISODE_COLUMNS)
        if resume_frame is not None:
            for log in (self.train, self.eval, self.eval_episodes):
                log.truncate_after(resume_frame)
        self.tb = None
        self._tb_video: Optional[bool] = None  # whether TensorBoard can take videos (moviepy)
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter
            except ImportError:  # tensorboard is a dependency, but an install without it keeps its CSV logs
                print("imssr: warning: TensorBoard is not installed: train.csv and eval.csv keep every row",
                      flush=True)
                return
            _quiet_tensorboard_disk_full()
            # purge_step drops events newer than the checkpoint on resume.
            with disk_full_as_error(run.tb_dir):
                self.tb = SummaryWriter(run.tb_dir, purge_step=None if resume_frame is None else resume_frame + 1)

    def relog_to_wandb(self) -> None:
        """On resume, log the CSV rows (up to the checkpoint) that the W&B run lacks, in frame
        order: those that W&B had not written when an earlier process was killed."""
        if self.wandb is None or not self.wandb.active:
            return
        rows = sorted(read_csv(self.train.path) + read_csv(self.eval.path), key=lambda row: float(row["frame"]))
        for row in rows:
            self.wandb.log(_series(row), int(float(row["frame"])), int(float(row["step"])))

    def rewrite_eval(self, history: list[dict]) -> None:
        """Rewrite the evaluation CSVs from a checkpoint's history (``row`` + ``returns``)."""
        for log in (self.eval, self.eval_episodes):
            atomic_write_text(log.path, ",".join(log.columns) + "\n")
        for item in history:
            self._write_eval(item["row"], item["returns"])

    def log_train(self, row: dict) -> None:
        self.train.write(row)
        self._scalars(row)

    def log_eval(self, row: dict, returns: Iterable[float]) -> None:
        self._write_eval(row, returns)
        self._scalars(row)

    def _write_eval(self, row: dict, returns: Iterable[float]) -> None:
        """Append one evaluation: its summary row and one row per episode."""
        self.eval.write(row)
        for episode in episode_rows(row, returns):
            self.eval_episodes.write(episode)

    def log_video(self, mode: str, frames: list[np.ndarray], frame: int, step: int, fmt: str) -> str:
        """One evaluation episode in scene ``mode`` (``(H, W, 3)`` uint8 frames) as
        ``videos/step_<step>_<mode>.<fmt>``, to TensorBoard and to W&B; returns the file's path."""
        path = save_video(frames, self.run.video_path(f"step_{step:09d}_{mode}.{fmt}"), fps=VIDEO_FPS)
        if self.tb is not None and self._tensorboard_takes_video():
            # (N, T, C, H, W) uint8, one video.
            clip = np.moveaxis(np.stack(frames), -1, 1)[None]
            self._to_tensorboard(lambda tb: tb.add_video(f"eval/{mode}/video", clip, global_step=frame, fps=VIDEO_FPS))
        if self.wandb is not None:
            self.wandb.log_file(f"media/{mode}_video", path, frame, step)
        return path

    def log_image(self, key: str, path: str, frame: int, step: int) -> None:
        """A PNG (the learning curve) to W&B (TensorBoard plots its own curves)."""
        if self.wandb is not None:
            self.wandb.log_file(f"media/{key}", path, frame, step)

    @property
    def wants_media(self) -> bool:
        """Whether a logger that takes pictures (W&B) is on."""
        return self.wandb is not None and self.wandb.active

    def _tensorboard_takes_video(self) -> bool:
        # TensorBoard's add_video encodes through moviepy (its `editor` module), which imssr does
        # not depend on: without it the file is still written, and one note says why TB has none.
        if self._tb_video is None:
            try:
                import moviepy.editor  # noqa: F401
                self._tb_video = True
            except ImportError:
                self._tb_video = False
                print("imssr: note: evaluation videos go to RUN/videos only, not to TensorBoard "
                      "(its add_video needs moviepy < 2: pip install 'moviepy<2')", flush=True)
        return self._tb_video

    def _scalars(self, row: dict) -> None:
        values, frame = _series(row), int(row["frame"])

        def add(tb) -> None:
            for key, value in values.items():
                tb.add_scalar(key, value, global_step=frame)

        self._to_tensorboard(add)
        if self.wandb is not None:
            self.wandb.log(values, frame, int(row["step"]))

    def _to_tensorboard(self, write: Callable[[Any], Any]) -> None:
        """``write(writer)`` to TensorBoard, if on.  TensorBoard writes in a thread of its own; a
        full disk there comes back here (the next add or flush re-raises it) and turns TensorBoard
        off with one warning line: the run is recorded in its CSV logs and checkpoints, which
        TensorBoard only shows, so its view is not worth the run (a full disk under the
        checkpoints still stops the run, at its next checkpoint)."""
        if self.tb is None:
            return
        try:
            with disk_full_as_error(self.run.tb_dir):
                write(self.tb)
        except ImssrError as exc:
            self.tb = None  # its writer thread has ended on the error
            print(f"imssr: warning: {exc}: TensorBoard stops here (train.csv and eval.csv keep every row)", flush=True)

    def close(self) -> None:
        """Flush and close TensorBoard (:meth:`_to_tensorboard` on a full disk) and W&B."""
        try:
            self._to_tensorboard(lambda tb: tb.close())  # SummaryWriter.close flushes first
            self.tb = None
        finally:
            if self.wandb is not None:
                self.wandb.finish()


def _quiet_tensorboard_disk_full() -> None:
    """Keep the traceback of TensorBoard's writer thread off stderr when the disk is full.

    The thread stores the error, which the next ``add_scalar`` / ``flush`` re-raises in the
    training thread (and :class:`Logger` turns into one warning line), and then raises it again to end
    itself, which Python prints as "Exception in thread ...".  Other errors print as usual."""
    previous = threading.excepthook
    if getattr(previous, "imssr_tensorboard", False):
        return

    def hook(args):
        if not (args.thread is not None and type(args.thread).__module__.startswith("tensorboard.")
                and is_disk_full(args.exc_value)):
            previous(args)

    hook.imssr_tensorboard = True
    threading.excepthook = hook


def open_logger(run: RunDir, cfg, resume_frame: Optional[int] = None) -> Logger:
    """The logs of the run ``run`` trained with ``cfg`` (CSV, TensorBoard and W&B as
    ``cfg.train`` says); a resumed run's (``resume_frame``: its checkpoint's frame) are cut back
    to its checkpoint and continue its W&B run."""
    wandb = None
    if cfg.train.wandb:
        # Imported here: W&B is an extra, and a run without it must not load it.
        from imssr.training.wandb_run import WandbRun

        wandb = WandbRun(cfg, run, resume=resume_frame is not None)
    return Logger(run, cfg.train.tensorboard, resume_frame=resume_frame, wandb=wandb)
