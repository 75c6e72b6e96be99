"""The end of README command 1 (``imssr demo``): a GIF of the trained policy and one line
that says what the user just saw and what the paper-scale command is.

The demo's settings live with the other presets (``imssr.presets.demo_config``); this module
only turns a finished demo run into something a newcomer can look at.
"""
from __future__ import annotations

from imssr.config import RunConfig
from imssr.plots.media import save_video
from imssr.rundir import RunDir
from imssr.training.evaluate import evaluate
from imssr.training.logger import read_csv

# One IM-CURL training step of the paper preset (batch 128, sequential updates) on 2 CPU cores
# without AVX-512 (docs/performance.md, "Every base at the paper presets, fp32").
CPU_SECONDS_PER_PAPER_STEP = 2.37
PAPER_STEPS = 500_000


def record_episode(trainer, path: str) -> str:
    """Run one deterministic evaluation episode of ``trainer``'s agent in its first evaluation
    scene and save what the agent sees as a GIF at the task's real-time rate."""
    frames: list = []
    evaluate(trainer.agent, next(iter(trainer.eval_envs.values())), 1, record=frames)
    # One frame per agent step; dm_control's control step is 10 ms for cartpole, so
    # 100 / action_repeat frames per second plays the episode in real time.
    fps = 100 / trainer.cfg.env.action_repeat
    return save_video(frames, path, fps=fps)


def summary(cfg: RunConfig, run: RunDir, minutes: float, gif: str, png: str) -> str:
    """The demo's last line: what the curve shows, where the files are, the paper-scale command."""
    rows = [r for r in read_csv(run.eval_log) if r["mode"] == cfg.env.mode]
    first, best, last = rows[0], max(rows, key=lambda r: float(r["return_mean"])), rows[-1]
    ret = lambda r: f"{float(r['return_mean']):.0f} at agent step {int(r['step']):,}"  # noqa: E731
    best_text = "" if best is last else f" (best {ret(best)})"
    untrained = " (before any update)" if int(first["step"]) <= cfg.train.seed_steps else ""
    days = PAPER_STEPS * CPU_SECONDS_PER_PAPER_STEP / 86_400
    return (f"imssr: demo done in {minutes:.0f} min. {cfg.algo} on {cfg.env.task}, mean evaluation return "
            f"over {int(last['episodes'])} episodes: {ret(first)}{untrained} -> {ret(last)}{best_text}. "
            f"Curve: {png}; the trained policy: {gif}. A short run on the dense task, not a result: "
            f"the paper's runs are `imssr train --algo im-curl --task cartpole_swingup_sparse --seeds 1-5 "
            f"--out runs/im-curl --device cuda` ({PAPER_STEPS:,} agent steps each, about {days:.0f} days "
            f"per seed on 2 CPU cores without AVX-512: use a GPU).")
