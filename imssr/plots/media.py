"""Pictures of scenes: a labelled montage PNG (one frame per mode) and episode videos."""
from __future__ import annotations

import os

import numpy as np

from imssr.config import VIDEO_FORMATS
from imssr.envs import MODES, get_task, make_env
from imssr.errors import ImssrError
from imssr.files import atomic_path
from imssr.plots import pyplot


def save_montage(frames: dict[str, np.ndarray], path: str, title: str = "") -> str:
    """One ``(H, W, 3)`` frame per mode side by side (4 per row), labelled, as a PNG."""
    if not frames:
        raise ImssrError("no frames for the montage")
    cols = min(4, len(frames))
    rows = -(-len(frames) // cols)
    fig, axes = pyplot().subplots(rows, cols, figsize=(2.6 * cols, 2.8 * rows + (0.3 if title else 0)), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, (mode, frame) in zip(axes.flat, frames.items()):
        ax.imshow(frame, interpolation="nearest")
        ax.set_title(mode, fontsize=10)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save_png(fig, path)


def save_png(fig, path: str) -> str:
    """Write a matplotlib figure as a PNG at its own dpi, atomically (parent folders made), and close it."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi="figure", format="png")
    pyplot().close(fig)
    return path


def save_video(frames: list[np.ndarray], path: str, fps: float = 25) -> str:
    """Write ``(H, W, 3)`` uint8 frames as a gif or an mp4 (by the file suffix)."""
    import imageio.v2 as imageio

    fmt = os.path.splitext(path)[1].lstrip(".").lower()
    if fmt not in VIDEO_FORMATS:
        raise ImssrError(f"video format must be one of {', '.join(VIDEO_FORMATS)}, got {path}")
    if not frames:
        raise ImssrError("no frames to write")
    with atomic_path(path) as tmp:
        if fmt == "gif":
            imageio.mimsave(tmp, frames, format="GIF", duration=1000 / fps, loop=0)
        else:
            # 100 px frames: a macro block of 4 avoids ffmpeg's resize to a multiple of 16.
            with imageio.get_writer(tmp, format="FFMPEG", fps=fps, codec="libx264",
                                    macro_block_size=4, quality=8) as writer:
                for frame in frames:
                    writer.append_data(frame)
    return path


def scenes_montage(task: str, path: str, seed: int = 0, steps: int = 20, footage: str = "") -> str:
    """A montage PNG of ``task`` in every scene, each after ``steps`` random agent steps
    (``imssr modes --montage``); video scenes draw unseen (test) footage."""
    get_task(task)
    frames = {}
    for mode in MODES:
        env = make_env(task, seed=seed, mode=mode, footage_split="test", footage_path=footage)
        try:
            env.action_space.seed(seed)
            obs, _ = env.reset()
            for _ in range(steps):
                obs, *_ = env.step(env.action_space.sample())
            frames[mode] = np.moveaxis(obs[-3:], 0, -1)
        finally:
            env.close()
    return save_montage(frames, path, f"{task}: every scene (seed {seed})")
