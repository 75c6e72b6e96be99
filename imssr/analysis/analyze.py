"""``imssr analyze``: measure the two terms that the paper's Section III bounds the intrinsic
reward by, on the states of a trained run (docs/analysis.md).

The run directory is only read (no lock, as ``imssr evaluate``); the outputs go to ``RUN/analysis/``.

"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from imssr.analysis.adapter import batch_size, fix_draws
from imssr.analysis.measures import (first_visit, knn_distance, nuisance_distance, signal_of_states, standardise,
                                     state_coordinates)
from imssr.analysis.report import plot_correlations, save_extremes, spearman_ci, write_rows
from imssr.analysis.states import SOURCES, StateSample, collect
from imssr.envs import env_from_config
from imssr.envs.scenes import get_mode
from imssr.errors import ImssrError
from imssr.rundir import RunDir, as_run_dir
from imssr.seeds import ANALYSIS_ENV_SEED_OFFSET, ANALYSIS_ROLLOUT_SEED_OFFSET, ANALYSIS_SCENE_SEED_OFFSET
from imssr.training.build import agent_at, resolve_device, restore_agent

DEFAULT_MODES = ("color_hard", "video_hard", "distracting_hard")
"""The paper's two test scenes and the hardest Distracting-Control shift (colour, background, camera)."""


@dataclass
class AnalysisOptions:
    """What ``imssr analyze`` measures and where it writes."""

    checkpoints: list[str] = field(default_factory=list)
    """Checkpoint files or agent steps (``imssr evaluate --checkpoint`` syntax); empty: every
    retained ``step-*.pt`` (``latest.pt`` when none is retained)."""
    states: int = 64
    """Transitions to analyse (fewer if the source holds fewer)."""
    modes: tuple[str, ...] = DEFAULT_MODES
    """Test scenes ``n`` whose renderings are compared with ``training`` (``n0``)."""
    out: Optional[str] = None
    """Output directory (None: ``RUN/analysis``)."""
    device: str = "cpu"
    """Torch device of the encoders."""
    seed: int = 0
    """Seed of the state draw, the crops, the scenes' nuisance draws and the bootstrap."""
    neighbors: int = 5
    """``k`` of the k-NN novelty."""
    top_k: int = 4
    """States shown per row of the montage (highest and lowest signal)."""
    reps: int = 1000
    """Bootstrap resamples per confidence interval."""
    source: str = "auto"
    """``replay``, ``rollouts`` or ``auto`` (the replay when it recorded physics states)."""

    def validate(self) -> None:
        for value, name in ((self.states, "states"), (self.neighbors, "neighbors"), (self.top_k, "top-k"),
                            (self.reps, "reps")):
            if value < 1:
                raise ImssrError(f"--{name} must be >= 1, got {value}")
        if self.states < 3:
            raise ImssrError(f"--states must be >= 3 for a rank correlation, got {self.states}")
        if not self.modes:
            raise ImssrError("--modes names no scene; give at least one, e.g. color_hard")
        for mode in self.modes:
            get_mode(mode)
        if self.source not in SOURCES:
            raise ImssrError(f"unknown --source {self.source!r}; valid: {', '.join(SOURCES)}")
        if self.out is not None and not self.out.strip():
            raise ImssrError("--out is empty; give a path, or omit --out for RUN/analysis")


@dataclass
class AnalysisResult:
    """Where the outputs are, and what the analysis found (one entry per checkpoint x measure)."""

    states_csv: str
    correlations_csv: str
    figure: str
    montage: str
    correlations: list[dict]
    source: str
    note: str
    rerender_exact: Optional[int] = None
    """Of the analysed ``o'`` stacks, how many rendered again in ``training`` equal the stored
    pixels (None when the run trained in another scene or the states are rollouts)."""


def analyze_run(run_dir: RunDir | str, opts: AnalysisOptions, log=print) -> AnalysisResult:
    """Analyse the run in ``run_dir`` (its path or :class:`~imssr.rundir.RunDir`); see the module
    docstring and docs/analysis.md."""
    opts.validate()
    run = as_run_dir(run_dir).require()
    cfg = run.read_config()
    if not cfg.intrinsic.enabled:
        raise ImssrError(f"the run's algorithm {cfg.algo} has no intrinsic reward to analyse (choose an im-, "
                         "+rnd or +re3 algorithm's run)")
    ckpts = {}
    for spec in opts.checkpoints or run.numbered_checkpoints() or [run.latest]:
        ckpt = run.checkpoint(str(spec)).checkpoint
        ckpts.setdefault(int(ckpt.step), ckpt)
    steps = sorted(ckpts)
    latest, _, warn = run.checkpoint(verb="analysing")
    if warn:
        log(f"imssr: {warn}")
    resolve_device(opts.device)  # a bad device fails before any env is built
    e = cfg.env
    out = opts.out or run.analysis_dir
    env = env_from_config(e, seed=opts.seed + ANALYSIS_ENV_SEED_OFFSET, mode="training", footage_split="train")
    envs = {"training": env}  # every env the analysis builds, each closed at its end
    try:
        # The newest analysed checkpoint's agent; every other checkpoint loads into the same one.
        agent = agent_at(ckpts[steps[-1]], cfg, device=opts.device, env=env).agent
        rng = np.random.default_rng(opts.seed)
        if e.mode != "training":
            envs["rollouts"] = env_from_config(e, seed=opts.seed + ANALYSIS_ROLLOUT_SEED_OFFSET, footage_split="train")
        sample = collect(run, cfg, latest, opts.states, rng, opts.source, envs.get("rollouts", env),
                         lambda: restore_agent(agent, ckpts[steps[-1]]))
        log(f"imssr: analysing {len(sample)} states of {run.path} ({sample.note}) at agent step(s) "
            f"{', '.join(f'{s:,}' for s in steps)}")
        # The same physics states in n0 (training) and in each test scene n.
        clean = np.stack([env.render_stack(s) for s in sample.stack_physics])
        exact = (int(sum(np.array_equal(a, b) for a, b in zip(clean, sample.batch["next_obs"])))
                 if sample.source == "replay" and e.mode == "training" else None)
        shifted = {}
        for i, mode in enumerate(opts.modes):
            if mode not in envs:
                envs[mode] = env_from_config(e, seed=opts.seed + ANALYSIS_SCENE_SEED_OFFSET + i, mode=mode,
                                             footage_split="test")
            shifted[mode] = np.stack([envs[mode].render_stack(s) for s in sample.stack_physics])
        novelty_all, per_step_novelty, first = _novelty(sample, env, steps, opts.neighbors)
        for note in _novelty_notes(novelty_all, per_step_novelty, opts.neighbors, len(sample.pool_step)):
            log(f"imssr: note: {note}")
        padding = sample.buffer.gather(sample.buffer.sample_indices(batch_size(agent)))
        rows, corr = [], []
        for step in steps:
            restore_agent(agent, ckpts[step])
            # The same crops and extra views at every checkpoint: only the weights differ.
            fix_draws(agent, opts.seed)
            signal = signal_of_states(agent, sample.batch, padding)
            nuisance = {m: nuisance_distance(agent, clean, shifted[m]) for m in opts.modes}
            mean_nuisance = np.mean([nuisance[m] for m in opts.modes], axis=0)
            novelty = per_step_novelty[step]
            for i in range(len(sample)):
                rows.append({"checkpoint_step": step, "state": i, "slot": int(sample.slot[i]),
                             "agent_step": int(sample.agent_step[i]),
                             "step_in_episode": int(sample.buffer.step_in_episode[sample.slot[i]]),
                             "reward": float(sample.batch["reward"][i]), "signal": float(signal[i]),
                             "novelty": float(novelty[i]), "novelty_all": float(novelty_all[i]),
                             "first_visit_step": int(first[i]),
                             "seen_by_checkpoint": "" if first[i] < 0 else int(first[i] <= step),
                             **{f"nuisance_{m}": float(nuisance[m][i]) for m in opts.modes},
                             "nuisance_mean": float(mean_nuisance[i])})
            against = {"novelty": novelty, "novelty_all": novelty_all, "nuisance_mean": mean_nuisance,
                       **{f"nuisance_{m}": nuisance[m] for m in opts.modes}}
            for key, x in against.items():
                c = spearman_ci(signal, x, opts.reps, opts.seed)
                # The medians show how the terms themselves move between checkpoints (the paper
                # argues the nuisance term vanishes as the encoder converges).
                corr.append({"checkpoint_step": step, "against": key, **c, "signal_median": float(np.median(signal)),
                             "median": float(np.nanmedian(x)) if np.isfinite(x).any() else float("nan")})
                log(f"  step {step:,}: signal vs {key}: Spearman rho {c['rho']:.3f} "
                    f"(95% CI {c['ci_low']:.3f} to {c['ci_high']:.3f}, n {c['n']}); median {corr[-1]['median']:.3g}")
        title = f"{cfg.algo} on {e.task}, seed {cfg.train.seed}: {len(sample)} states ({sample.source})"
        states_csv = write_rows(os.path.join(out, "states.csv"), rows)
        corr_csv = write_rows(os.path.join(out, "correlations.csv"), corr)
        figure = plot_correlations(rows, corr, opts.modes, os.path.join(out, "analysis.png"), title)
        montage = _montage(sample, signal, per_step_novelty[steps[-1]], opts.top_k,
                           os.path.join(out, "montage.png"), f"{title}; step {steps[-1]:,}: "
                           "top: highest intrinsic signal, bottom: lowest")
    finally:
        for each in envs.values():
            each.close()
    if exact is not None:
        log(f"imssr: re-rendered in training, {exact} of {len(sample)} stacks equal the stored frames")
    return AnalysisResult(states_csv, corr_csv, figure, montage, corr, sample.source, sample.note, exact)


def _novelty(sample: StateSample, env, steps: list[int], k: int):
    """k-NN novelty against the whole pool and, per checkpoint, against the states stored up to
    its agent step (what its encoder could have trained on); the first-visit step of each state."""
    coords = state_coordinates(env.physics, sample.pool_physics)
    pool = standardise(coords, coords)
    query = pool[sample.slot]
    novelty_all = knn_distance(query, pool, k, exclude=sample.slot)
    radius = float(np.nanmedian(novelty_all)) if np.isfinite(novelty_all).any() else 0.0
    first = first_visit(query, pool, sample.pool_step, radius, sample.agent_step)
    per_step = {}
    known = sample.pool_step >= 0
    for step in steps:
        seen = pool.copy()
        seen[~known | (sample.pool_step > step)] = np.nan
        per_step[step] = knn_distance(query, seen, k, exclude=sample.slot) if known.any() else novelty_all
    return novelty_all, per_step, first


def _novelty_notes(novelty_all: np.ndarray, per_step: dict[int, np.ndarray], k: int, pool: int) -> list[str]:
    """What leaves the novelty columns empty: fewer than ``k`` other states in the pool, or
    stored by a checkpoint's agent step."""
    if not np.isfinite(novelty_all).any():
        return [f"--neighbors {k} needs more than {k} states in the pool, which holds {pool}: the novelty "
                f"columns are empty; lower --neighbors"]
    empty = [step for step, x in per_step.items() if not np.isfinite(x).any()]
    return [f"fewer than {k + 1} states were stored by agent step(s) {', '.join(f'{s:,}' for s in empty)}: "
            f"the novelty column is empty there (novelty_all is not); lower --neighbors"] if empty else []


def _montage(sample: StateSample, signal: np.ndarray, novelty: np.ndarray, k: int, path: str, title: str) -> str:
    order = np.argsort(signal, kind="stable")
    k = min(k, len(order) // 2) or 1

    def item(i):
        frame = np.moveaxis(sample.batch["next_obs"][i][-3:], 0, -1)
        when = "" if sample.agent_step[i] < 0 else f", step {int(sample.agent_step[i]):,}"
        return frame, f"signal {signal[i]:.3g}\nnovelty {novelty[i]:.2f}{when}"

    return save_extremes([item(i) for i in order[::-1][:k]], [item(i) for i in order[:k]], path, title)
