"""The notebook API: train a run and load a trained one in a few lines of Python.

    import imssr
    run = imssr.train("im-curl", "cartpole_swingup", out="runs/nb", steps=...)
    run = imssr.load_run("runs/nb")                   # or checkpoint="5000" / a file
    run.act(obs); run.evaluate(mode="color_hard", episodes=5); run.curves()

:func:`train` is ``imssr train``; :class:`Run` only reads its run directory.
"""
from __future__ import annotations

import os
import warnings
from typing import Any, Optional, Sequence

import numpy as np

from imssr.config import RunConfig
from imssr.crash import report_native_crashes
from imssr.envs import env_from_config
from imssr.errors import ImssrError
from imssr.files import read_csv
from imssr.rundir import (EVAL_LOG, EVAL_EPISODES_LOG, EVALUATE_EPISODES_LOG, EVALUATE_LOG, TRAIN_LOG, RunDir,
                          as_run_dir)
from imssr.seeds import evaluation_seed
from imssr.training.build import load_agent
from imssr.training.evaluate import eval_row, evaluate
from imssr.training import entry
from imssr.training.stop import TrainingInterrupted

CURVES = tuple(name.removesuffix(".csv") for name in (EVAL_LOG, TRAIN_LOG, EVAL_EPISODES_LOG, EVALUATE_LOG,
                                                      EVALUATE_EPISODES_LOG))
"""The run's CSV logs that :meth:`Run.curves` reads (``RUN/<name>.csv``)."""


class Run:
    """A trained run, loaded from its directory: the config, one checkpoint's agent, its logs.

    Args:
        run_dir: the run directory (``config.json``, ``checkpoints/``, the CSV logs): its path or
            its :class:`~imssr.rundir.RunDir`.
        checkpoint: as ``imssr evaluate --checkpoint``: a checkpoint file, or the agent step of a
            retained ``step-*.pt``; None: the latest that verifies.
        device: torch device of the agent (``auto`` allowed).
    """

    def __init__(self, run_dir: RunDir | str, checkpoint: Optional[str] = None, device: str = "cpu"):
        report_native_crashes()  # a notebook's kernel that dies says why in its log
        self.run_dir = as_run_dir(run_dir)
        self.dir = self.run_dir.path
        loaded = load_agent(self.run_dir, checkpoint, device=device, verb="loading")
        if loaded.note:
            warnings.warn(loaded.note, stacklevel=2)
        self.config: RunConfig = loaded.config
        self.step: int = loaded.step
        """Agent step of the loaded checkpoint."""
        self.frame: int = loaded.frame
        """Environment frame of the loaded checkpoint."""
        self.observation_shape: tuple = loaded.obs_shape
        self.agent = loaded.agent

    def __repr__(self) -> str:
        return (f"Run({self.dir!r}: {self.config.algo} on {self.config.env.task}, seed {self.config.train.seed}, "
                f"checkpoint at agent step {self.step:,})")

    def make_env(self, mode: Optional[str] = None, seed: Optional[int] = None):
        """A gymnasium env of the run's task in scene ``mode`` (None: the scene it trained in),
        built as the run's evaluation envs are (unseen footage); ``seed`` None: as
        :meth:`evaluate`'s."""
        seed = evaluation_seed(self.config.train.seed) if seed is None else seed
        return env_from_config(self.config.env, seed=seed, mode=mode, footage_split="test")

    def act(self, obs, deterministic: bool = True) -> np.ndarray:
        """The agent's action in [-1, 1] for one observation of the run's envs (uint8, stacked
        frames, shape :attr:`observation_shape`); deterministic: the mean action, as evaluated."""
        obs = np.asarray(obs)
        if obs.shape != self.observation_shape or obs.dtype != np.uint8:
            raise ImssrError(f"act() takes one observation of the run's envs: uint8 of shape "
                             f"{self.observation_shape}, got {obs.dtype} of shape {obs.shape}")
        return self.agent.act(obs, deterministic=deterministic)

    def evaluate(self, mode: Optional[str] = None, episodes: int = 10, seed: Optional[int] = None) -> dict:
        """Returns of ``episodes`` deterministic episodes in scene ``mode`` (None: the training
        scene), as ``imssr evaluate`` measures them but written nowhere: the ``eval.csv`` summary
        (``return_mean``, ``return_std``, ...) with ``returns``, one per episode."""
        if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
            raise ImssrError(f"episodes must be a positive integer, got {episodes!r}")
        env = self.make_env(mode, seed)
        try:
            returns = evaluate(self.agent, env, episodes)
        finally:
            env.close()
        return {**eval_row(self.frame, self.step, env.mode, returns), "returns": returns}

    def curves(self, name: str = "eval"):
        """The run's log ``RUN/<name>.csv`` (:data:`CURVES`) as a pandas DataFrame when pandas is installed, else a
        list of dicts with numbers as numbers; empty when the run has not written it."""
        if name not in CURVES:
            raise ImssrError(f"unknown log {name!r}; choose from {', '.join(CURVES)}")
        path = self.run_dir.log(name)
        try:
            import pandas as pd
        except ImportError:
            return _typed(read_csv(path))
        return pd.read_csv(path) if os.path.exists(path) else pd.DataFrame()


def load_run(run_dir: RunDir | str, checkpoint: Optional[str] = None, device: str = "cpu") -> Run:
    """The trained run in ``run_dir`` (see :class:`Run`)."""
    return Run(run_dir, checkpoint=checkpoint, device=device)


def train(algo: str = "im-curl", task: str = "cartpole_swingup", out: Optional[str] = None, *,
          steps: Optional[int] = None, frames: Optional[int] = None, seed: Optional[int] = None,
          seeds: Optional[Sequence[int]] = None, device: Optional[str] = None, demo: bool = False,
          overrides: Sequence[str] = (), resume: bool = False, progress: bool = True) -> Run | list[Run]:
    """Train a run as ``imssr train`` does and load it (:class:`Run`, latest checkpoint; with
    ``seeds``, a list of them).

    Args:
        algo, task: as ``--algo`` / ``--task`` (``imssr algos``, ``imssr tasks``); the run starts
            from their paper preset (``demo``: the demo's settings).
        out: the run directory; None: ``runs/<task>/<algo>/seed_<seed>``.  With ``seeds``: the
            folder of the seeds' run directories, ``out/seed_<n>``.
        steps: budget in agent steps (``frames``: in environment frames instead); None: the
            preset's (the paper's T = 500,000 agent steps).
        seed: the run's seed; None: the preset's.
        seeds: train these seeds in one process, in lockstep, as ``--seeds`` does, and return a
            list of runs, one per seed.
        device: torch device (``cpu``, ``cuda``, ``auto``); None: the preset's (cpu).
        overrides: ``section.field=value`` strings, as ``--set``.
        resume: continue the run in ``out`` from its checkpoint (the saved config, a larger budget
            allowed).
        progress: show progress (``train.progress``): a bar on a terminal, else (a notebook, a
            log) a line every minute; False: neither.

    An interrupt (SIGINT: the notebook's stop button, Ctrl-C) stops after the current agent step with a checkpoint
    and raises ``KeyboardInterrupt``; ``resume=True`` continues from there.
    """
    values: dict[str, Any] = {"train.progress": progress}
    for field, value in (("train.steps", steps), ("train.seed", seed), ("train.device", device)):
        if value is not None:
            values[field] = value
    if isinstance(overrides, str):
        raise ImssrError("overrides is a list of 'section.field=value' strings, e.g. ['train.eval_episodes=5']")
    if resume and out is None:
        raise ImssrError("resume=True needs out, the run directory to continue")
    if seeds is not None:
        seeds = list(seeds)
        if not seeds or len(set(seeds)) != len(seeds) or \
                not all(isinstance(s, int) and not isinstance(s, bool) for s in seeds):
            raise ImssrError(f"seeds is a list of different integers, e.g. [1, 2, 3], got {seeds!r}")
        if out is None:
            raise ImssrError("seeds needs out, the folder of the seeds' run directories")
        if seed is not None:
            raise ImssrError("give seed (one run) or seeds (several), not both")
    request = entry.TrainRequest(algo=None if resume else algo, task=None if resume else task, out=out, seeds=seeds,
                                 resume=resume, demo=demo, values=values, frames=frames, overrides=list(overrides))
    try:
        trained = entry.train(request)
    except TrainingInterrupted as exc:
        again = f"out={out if out is not None else exc.out!r}" + ("" if seeds is None else f", seeds={seeds}")
        raise KeyboardInterrupt(f"stopped at agent step {exc.step} with a checkpoint; continue with "
                                f"imssr.train({again}, resume=True)") from None
    loaded = [load_run(run, device=cfg.train.device) for cfg, run in trained]
    return loaded if seeds is not None else loaded[0]


def _typed(rows: list[dict]) -> list[dict]:
    """CSV rows with each column's cells as pandas reads them: int where every cell of the
    column is an integer, else float where every cell is a number (empty: None), else text."""
    if not rows:
        return []
    kinds = {}
    for column in rows[0]:
        cells = [r[column] for r in rows if r[column] not in (None, "")]
        kinds[column] = next((kind for kind in (int, float) if all(_parses(kind, c) for c in cells)), str)
    return [{k: None if v in (None, "") else kinds[k](v) for k, v in row.items()} for row in rows]


def _parses(kind, text: str) -> bool:
    try:
        kind(text)
        return True
    except ValueError:
        return False
