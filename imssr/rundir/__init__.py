"""Run directories: :class:`RunDir`, their layout and life (:mod:`~imssr.rundir.directory`, made of
the parts in ``layout``, ``records``, ``checkpoints`` and ``batch``), one checkpoint file
(:mod:`~imssr.rundir.checkpoint`) and the one-writer lock (:mod:`~imssr.rundir.lock`)."""
from imssr.rundir.batch import batch_checkpoints, first_set_leftovers
from imssr.rundir.checkpoints import CheckpointFile
from imssr.rundir.directory import RunDir, as_run_dir
from imssr.rundir.layout import (ANALYSIS_DIR, CHECKPOINT_DIR, CONFIG_FILE, CSV_LOGS, DIVERGED, DONE_FILE, ENDINGS,
                                 EPISODE_GIF, EVAL_EPISODES_LOG, EVAL_LOG, EVALUATE_EPISODES_LOG, EVALUATE_LOG, FAILED,
                                 FINISHED, FRAMES_FILE, INTERRUPTED, LATEST_CHECKPOINT, LEARNING_CURVE_FILE,
                                 MONTAGE_FILE, NEW, NUMBERED_CHECKPOINT, PROVENANCE_FILE, REPLAY_FILE, RUNNING,
                                 SEED_DIR, STATUS_FILE, SWEEP_LOG, TB_DIR, TRAIN_LOG, TRAINING_LOGS, VIDEOS_DIR,
                                 WANDB_RUN_FILE, RunPath, parse_run_path, run_path)
from imssr.rundir.lock import LOCK_FILE

__all__ = ["ANALYSIS_DIR", "CHECKPOINT_DIR", "CONFIG_FILE", "CSV_LOGS", "DIVERGED", "DONE_FILE", "ENDINGS",
           "EPISODE_GIF", "EVAL_EPISODES_LOG", "EVAL_LOG", "EVALUATE_EPISODES_LOG", "EVALUATE_LOG", "FAILED",
           "FINISHED", "FRAMES_FILE", "INTERRUPTED", "LATEST_CHECKPOINT", "LEARNING_CURVE_FILE", "LOCK_FILE",
           "MONTAGE_FILE", "NEW", "NUMBERED_CHECKPOINT", "PROVENANCE_FILE", "REPLAY_FILE", "RUNNING", "SEED_DIR",
           "STATUS_FILE", "SWEEP_LOG", "TB_DIR", "TRAIN_LOG", "TRAINING_LOGS", "VIDEOS_DIR", "WANDB_RUN_FILE",
           "CheckpointFile", "RunDir", "RunPath", "as_run_dir", "batch_checkpoints", "first_set_leftovers",
           "parse_run_path", "run_path"]
