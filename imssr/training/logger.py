"""CSV logs (always) and TensorBoard (optional), both resumable.

Every row carries ``frame`` (environment frames) and ``step`` (agent steps).
On resume, rows newer than the checkpoint are dropped so that a killed run
continued from its checkpoint leaves the same files as an uninterrupted one.
"""
from __future__ import annotations

import csv
import fcntl
import math
import os
import shutil
import threading
from typing import Iterable, Optional

from imssr.utils import atomic_write_text, disk_full_as_error, is_disk_full

TRAIN_COLUMNS = ["frame", "step", "episode", "episode_return", "episode_frames", "fps",
                 "critic_loss", "actor_loss", "alpha_loss", "alpha", "entropy", "q_mean",
                 "aux_loss", "rnd_loss", "r_int_raw", "r_int_raw_std", "r_int_mean", "r_int_std", "bonus_std", "beta", "updates", "wall_time"]
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
        with disk_full_as_error(self.path), open(self.path, "a", newline="") as fh:
            csv.DictWriter(fh, self.columns, extrasaction="ignore").writerow(
                {k: _fmt(row.get(k)) for k in self.columns})
            fh.flush()

    def truncate_after(self, frame: int) -> None:
        """Keep only rows with ``frame <= frame`` (used on resume)."""
        rows = read_csv(self.path)
        # A process killed mid-write can leave a partial last line: drop it.
        complete = [r for r in rows if None not in r.values() and None not in r and _is_number(r.get("frame"))]
        kept = [r for r in complete if int(float(r["frame"])) <= frame]
        lines = [",".join(self.columns)]
        for r in kept:
            lines.append(",".join(_quote(r.get(c, "")) for c in self.columns))
        atomic_write_text(self.path, "\n".join(lines) + "\n")


def _fmt(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        if math.isnan(v):
            return ""
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


def read_csv(path: str) -> list[dict]:
    if not os.path.exists(path):
        return []
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def episode_rows(row: dict, returns: Iterable[float]) -> list[dict]:
    """The per-episode rows of the evaluation summarised by ``row``."""
    return [{"frame": row["frame"], "step": row["step"], "mode": row["mode"], "episode": i, "return": ret}
            for i, ret in enumerate(returns)]


def write_eval(summary: CSVLog, episodes: CSVLog, row: dict, returns: Iterable[float]) -> None:
    """Append one evaluation: its summary row and one row per episode."""
    summary.write(row)
    for episode in episode_rows(row, returns):
        episodes.write(episode)


def append_locked(path: str, columns: list[str], rows: list[dict]) -> None:
    """Append ``rows`` to a CSV file that several processes may append to at once (two ``imssr
    evaluate`` of one run): under an exclusive ``flock`` of the file, so the rows of one call stay
    together, with the header first when the file is new."""
    with disk_full_as_error(path), open(path, "a", newline="") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)  # released when the file closes
        if fh.seek(0, os.SEEK_END) == 0:
            fh.write(",".join(columns) + "\n")
        writer = csv.DictWriter(fh, columns, extrasaction="ignore")
        writer.writerows({k: _fmt(r.get(k)) for k in columns} for r in rows)
        fh.flush()


class Logger:
    """``train.csv``, ``eval.csv``, ``eval_episodes.csv`` and TensorBoard under ``out_dir``."""

    def __init__(self, out_dir: str, tensorboard: bool = True, resume_frame: Optional[int] = None):
        if resume_frame is None:
            # A fresh run: logs left by a run killed before its first checkpoint are stale.
            for name in ("train.csv", "eval.csv", "eval_episodes.csv"):
                if os.path.exists(os.path.join(out_dir, name)):
                    os.unlink(os.path.join(out_dir, name))
            shutil.rmtree(os.path.join(out_dir, "tb"), ignore_errors=True)
        self.train = CSVLog(os.path.join(out_dir, "train.csv"), TRAIN_COLUMNS)
        self.eval = CSVLog(os.path.join(out_dir, "eval.csv"), EVAL_COLUMNS)
        self.eval_episodes = CSVLog(os.path.join(out_dir, "eval_episodes.csv"), EVAL_EPISODE_COLUMNS)
        if resume_frame is not None:
            for log in (self.train, self.eval, self.eval_episodes):
                log.truncate_after(resume_frame)
        self.tb = None
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter
            except ImportError:  # tensorboard is a dependency, but keep CSV logs working
                SummaryWriter = None
            if SummaryWriter is not None:
                _quiet_tensorboard_disk_full()
                self.tb_dir = os.path.join(out_dir, "tb")
                # purge_step drops events newer than the checkpoint on resume.
                self.tb = SummaryWriter(os.path.join(out_dir, "tb"), purge_step=None if resume_frame is None else resume_frame + 1)

    def rewrite_eval(self, history: list[dict]) -> None:
        """Rewrite the evaluation CSVs from a checkpoint's history (``row`` + ``returns``)."""
        for log in (self.eval, self.eval_episodes):
            atomic_write_text(log.path, ",".join(log.columns) + "\n")
        for item in history:
            write_eval(self.eval, self.eval_episodes, item["row"], item["returns"])

    def log_train(self, row: dict) -> None:
        self.train.write(row)
        self._tb("train", row, skip=("frame", "step", "episode"))

    def log_eval(self, row: dict, returns: Iterable[float]) -> None:
        write_eval(self.eval, self.eval_episodes, row, returns)
        self._tb(f"eval/{row['mode']}", row, skip=("frame", "step", "mode", "episodes"))

    def _tb(self, prefix: str, row: dict, skip: tuple) -> None:
        if self.tb is None:
            return
        # TensorBoard writes in a thread of its own; a full disk there comes back here (the
        # next add or flush re-raises it) and becomes the one-line error.
        with disk_full_as_error(self.tb_dir):
            for k, v in row.items():
                if k in skip or v is None or isinstance(v, str):
                    continue
                self.tb.add_scalar(f"{prefix}/{k}", float(v), global_step=int(row["frame"]))

    def close(self) -> None:
        if self.tb is not None:
            tb, self.tb = self.tb, None
            with disk_full_as_error(self.tb_dir):
                try:
                    tb.flush()
                finally:
                    tb.close()


def _quiet_tensorboard_disk_full() -> None:
    """Keep the traceback of TensorBoard's writer thread off stderr when the disk is full.

    The thread stores the error, which the next ``add_scalar`` / ``flush`` re-raises in the
    training thread (and :class:`Logger` reports in one line), and then raises it again to end
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
