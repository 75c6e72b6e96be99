"""A run's Weights & Biases run (the ``wandb`` extra, imported only when ``train.wandb`` is on).

The W&B run id is kept in the run directory (``wandb_run.json``), written before the W&B run starts, so a
``--resume`` (after a kill -9 too) continues the same W&B run (``resume="allow"``).  A resume
reads back what the run's earlier processes left in their ``.wandb`` files (a kill -9 loses what
W&B had not yet written there) and logs each series at each frame once: the CSV rows W&B lacks
are logged again (:meth:`imssr.training.logger.Logger.relog_to_wandb`), the rows it holds are
not, so a resume from a checkpoint older than W&B's last row adds no second row at a frame.  What
W&B holds is what the files under this machine's W&B directory say (``WANDB_DIR``, else the run
directory): a resume on another machine, without them, logs the run's rows again.  W&B is a
side channel: once the extra is there, nothing it does may stop a training.  An unwritable W&B
directory, a failed start or a failed log call prints one warning line and turns W&B off for
the rest of the process; the CSV logs (and TensorBoard) go on.
"""
from __future__ import annotations

import json
import os
import secrets
import tempfile
from typing import Optional

from imssr.config import RunConfig
from imssr.extras import require
from imssr.files import atomic_write_text
from imssr.rundir import RunDir
from imssr.training.wandb_records import logged_series, series_of

FLUSH_SECONDS = 1.0
"""How often W&B writes what it was given to the run's ``.wandb`` file (its own default: 15 s):
what a kill -9 can take from W&B (the CSV rows it lacks are logged again on resume)."""

def run_tags(cfg: RunConfig) -> list[str]:
    """The run's W&B tags: algo, task, seed and (algos with an intrinsic reward) beta_0."""
    tags = [cfg.algo, cfg.env.task, f"seed_{cfg.train.seed}"]
    if cfg.intrinsic.enabled:
        tags.append(f"beta0_{cfg.intrinsic.beta0!r}")
    return tags


def read_run_id(run: RunDir) -> Optional[str]:
    """The W&B run id kept in ``run`` (None when there is none or it is unreadable)."""
    try:
        with open(run.wandb_run_path) as fh:
            run_id = json.load(fh).get("id")
    except (OSError, ValueError, AttributeError):
        return None
    return run_id if isinstance(run_id, str) and run_id else None


class WandbRun:
    """Logs to one W&B run; every method is a no-op once W&B is off.

    Args:
        cfg: the run's config (the W&B run's config, project, group and tags).
        run: the run directory (the run id file; W&B's files go to ``RUN/wandb`` unless
            ``WANDB_DIR`` says otherwise).
        resume: continue the W&B run whose id ``run`` keeps (a new one if it keeps none).
    """

    def __init__(self, cfg: RunConfig, run: RunDir, resume: bool):
        # A missing extra is the user's error (they asked for W&B): one line, before training.
        self._wandb = require("wandb", "wandb")
        self.run = None
        self.held: set[tuple[str, int]] = set()
        run_id = read_run_id(run) if resume else None
        if run_id is None:
            # From the OS's entropy: the seeded random streams of the run are left alone.
            run_id = secrets.token_hex(6)
            atomic_write_text(run.wandb_run_path, json.dumps({"id": run_id}) + "\n")
        directory = os.environ.get("WANDB_DIR") or run.path
        problem = _unwritable(directory)
        if problem:
            self._off(f"its directory {directory} is not writable ({problem})")
            return
        t = cfg.train
        try:
            if resume:
                self.held = logged_series(directory, run_id)
            self.run = self._wandb.init(
                project=t.wandb_project, group=t.wandb_group or None, tags=run_tags(cfg),
                name=f"{cfg.algo} {cfg.env.task} seed {t.seed}", config=cfg.to_dict(), id=run_id,
                resume="allow", dir=directory, reinit="create_new",
                # imssr prints its own progress; W&B's console capture would duplicate it.
                settings=self._wandb.Settings(console="off", quiet=True, save_code=False,
                                              x_transaction_log_flush_interval=FLUSH_SECONDS))
            # Scalars are plotted against environment frames, as TensorBoard's global step.
            self.run.define_metric("frame")
            for prefix in ("train/*", "eval/*", "media/*"):
                self.run.define_metric(prefix, step_metric="frame")
        except Exception as exc:  # noqa: BLE001 - any W&B failure must leave training alone
            self._off(f"it failed to start: {_first_line(exc)}")

    @property
    def active(self) -> bool:
        return self.run is not None

    def log(self, values: dict, frame: int, step: int) -> None:
        """Scalars (``prefix/name``, one prefix) at environment frame ``frame`` (agent step
        ``step``), unless the W&B run holds that prefix at that frame."""
        if values and not self.holds(next(iter(values)), frame):
            self._call(lambda: self.run.log({**values, "frame": frame, "step": step}))

    def holds(self, key: str, frame: int) -> bool:
        """Whether an earlier process of the W&B run logged ``key``'s series at ``frame``."""
        return (series_of(key), frame) in self.held

    def log_file(self, key: str, path: str, frame: int, step: int) -> None:
        """A PNG file as a W&B image, a gif or mp4 file as a W&B video."""
        fmt = os.path.splitext(path)[1].lstrip(".")
        media = (lambda: self._wandb.Image(path)) if fmt == "png" else (lambda: self._wandb.Video(path, format=fmt))
        if not self.holds(key, frame):
            self._call(lambda: self.run.log({key: media(), "frame": frame, "step": step}))

    def finish(self) -> None:
        if self.run is not None:
            run, self.run = self.run, None
            try:
                run.finish()
            except Exception as exc:  # noqa: BLE001
                print(f"imssr: warning: W&B did not finish cleanly: {_first_line(exc)}", flush=True)

    def _call(self, fn) -> None:
        if self.run is None:
            return
        try:
            fn()
        except Exception as exc:  # noqa: BLE001 - W&B failing mid-run must not stop training
            self._off(f"a log call failed: {_first_line(exc)}")

    def _off(self, why: str) -> None:
        self.run = None
        print(f"imssr: warning: Weights & Biases is off for this run: {why}; the CSV logs (and TensorBoard) go on",
              flush=True)


def _unwritable(directory: str) -> str:
    """Why W&B could not write in ``directory`` (empty when it can)."""
    try:
        os.makedirs(directory, exist_ok=True)
        with tempfile.TemporaryFile(dir=directory):
            pass
    except OSError as exc:
        return exc.strerror or str(exc)
    return ""


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__
