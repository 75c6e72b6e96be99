"""Run directories: :class:`RunDir`, their layout and life (:mod:`~imssr.rundir.directory`, made of
the parts in ``layout``, ``records``, ``checkpoint`` and ``batch``) and the one-writer lock
(:mod:`~imssr.rundir.lock`)."""
from imssr.rundir.batch import batch_checkpoints, first_set_leftovers
from imssr.rundir.checkpoint import CheckpointFile
from imssr.rundir.directory import RunDir, as_run_dir
from imssr.rundir.layout import (CHECKPOINT_DIR, CONFIG_FILE, CSV_LOGS, DIVERGED, DONE_FILE, EVAL_EPISODES_LOG,
                                 EVAL_LOG, EVALUATE_EPISODES_LOG, EVALUATE_LOG, FAILED, FINISHED, INTERRUPTED,
                                 LATEST_CHECKPOINT, PROVENANCE_FILE, SEED_DIR, STATUS_FILE, SWEEP_LOG, TB_DIR,
                                 TRAIN_LOG, VIDEOS_DIR, WANDB_RUN_FILE, RunPath, parse_run_path, run_path)
from imssr.rundir.lock import LOCK_FILE

__all__ = ["CHECKPOINT_DIR", "CONFIG_FILE", "CSV_LOGS", "DIVERGED", "DONE_FILE", "EVAL_EPISODES_LOG", "EVAL_LOG",
           "EVALUATE_EPISODES_LOG", "EVALUATE_LOG", "FAILED", "FINISHED", "INTERRUPTED", "LATEST_CHECKPOINT",
           "LOCK_FILE", "PROVENANCE_FILE", "SEED_DIR", "STATUS_FILE", "SWEEP_LOG", "TB_DIR", "TRAIN_LOG",
           "VIDEOS_DIR", "WANDB_RUN_FILE", "CheckpointFile", "RunDir", "RunPath", "as_run_dir", "batch_checkpoints",
           "first_set_leftovers", "parse_run_path", "run_path"]
