"""Moving footage for video backgrounds (DMControl-GB video modes, distracting scenes).

Sources, in order of precedence:

* a user-supplied path (``--footage DIR`` / ``env.footage_dir`` / ``$IMSSR_FOOTAGE_DIR``): a
  video file, a folder of video files, a folder of frame folders (DAVIS-2017's
  ``JPEGImages/480p/<video>/*.jpg``), or one folder of frames;
* built-in footage made offline from the photographs installed packages ship and dm_control's
  sky textures: slow pans, zooms and drifts, played forwards then backwards so clips loop.

Clips are split into disjoint ``train`` and ``test`` pools, so an agent is tested on unseen
footage.  A clip is a uint8 array ``(T, size, size, 3)``.
"""
from __future__ import annotations

import functools
import itertools
import os
from pathlib import Path

import numpy as np
from PIL import Image

from imssr.data.images import IMAGE_SUFFIXES, _read_rgb, _square_resize, source_files
from imssr.errors import ImssrError

FOOTAGE_DIR_ENV = "IMSSR_FOOTAGE_DIR"
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".gif")
SPLITS = ("train", "test")

def footage_sources(split: str) -> list[Path]:
    """Pictures the built-in ``split`` footage is made from (disjoint from the other
    split and from the overlay images; dm_control's labmaze sky boxes included)."""
    if split not in SPLITS:
        raise ImssrError(f"unknown footage split {split!r}; valid: {', '.join(SPLITS)}")
    return source_files(f"footage_{split}")


def moving_clip(image, size: int, length: int, rng: np.random.Generator) -> np.ndarray:
    """A pan + zoom + drift across ``image`` (PIL), ``length`` frames, looped back and forth."""
    w, h = image.size
    short = min(w, h)
    s0, s1 = short * rng.uniform(0.35, 0.9, size=2)  # zoom between two window sizes
    starts = [(rng.uniform(0, w - s), rng.uniform(0, h - s)) for s in (s0, s1)]
    half = max(length // 2, 1)
    t = 0.5 - 0.5 * np.cos(np.pi * np.linspace(0.0, 1.0, half))  # eased in and out
    phase = rng.uniform(0, 2 * np.pi)
    frames = []
    for i, a in enumerate(t):
        s = (1 - a) * s0 + a * s1
        x = (1 - a) * starts[0][0] + a * starts[1][0]
        y = (1 - a) * starts[0][1] + a * starts[1][1]
        # A small wobble on top of the pan, like a hand-held camera.
        x += 0.02 * short * np.sin(phase + 2 * np.pi * i / half)
        y += 0.02 * short * np.cos(phase + 2 * np.pi * i / half)
        x, y = float(np.clip(x, 0, w - s)), float(np.clip(y, 0, h - s))
        frames.append(_square_resize(image, size, (x, y, x + s, y + s)).transpose(1, 2, 0))
    clip = np.stack(frames)
    return np.concatenate([clip, clip[::-1]])[:length] if length > 1 else clip


@functools.lru_cache(maxsize=8)
def builtin_footage(size: int, split: str = "test", clips: int = 8, length: int = 100,
                    seed: int = 0) -> tuple[np.ndarray, ...]:
    """``clips`` moving clips for ``split`` from that split's own pictures."""
    pool = footage_sources(split)
    if not pool:
        raise ImssrError("no built-in pictures found for footage (install scikit-image); "
                         f"or point --footage / ${FOOTAGE_DIR_ENV} at videos or frame folders")
    rng = np.random.default_rng([seed, SPLITS.index(split)])
    images = [_read_rgb(p) for p in pool]
    return tuple(moving_clip(images[i % len(images)], size, length, rng) for i in range(clips))


def read_video(path: Path, size: int, max_frames: int = 500) -> np.ndarray:
    """Frames of a video file, centre-square resized to ``size``."""
    import imageio.v2 as imageio  # heavy (ffmpeg plugins): only for user videos

    try:
        reader = imageio.get_reader(str(path))
        frames = [_square_resize(Image.fromarray(np.asarray(frame)[..., :3]), size).transpose(1, 2, 0)
                  for frame in itertools.islice(reader, max_frames)]
        reader.close()
    except Exception as exc:  # noqa: BLE001 - codec/container errors come in many types
        raise ImssrError(f"cannot read video {path}: {str(exc).splitlines()[0] if str(exc) else exc}") from None
    if not frames:
        raise ImssrError(f"video {path} has no frames")
    return np.stack(frames)


def _frame_folder(folder: Path, size: int, max_frames: int) -> list[np.ndarray]:
    """The clip of a folder of frames (its images in name order) as a list of one; [] when it holds no image."""
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)[:max_frames]
    return [np.stack([_square_resize(_read_rgb(p), size).transpose(1, 2, 0) for p in files])] if files else []


@functools.lru_cache(maxsize=8)
def load_footage(path: str, size: int, max_frames: int = 500, max_clips: int = 64) -> tuple[np.ndarray, ...]:
    """Every clip found at ``path`` (see the module docstring for the layouts)."""
    root = Path(path).expanduser()
    if not root.exists():
        raise ImssrError(f"footage not found: {root} (--footage, env.footage_dir or ${FOOTAGE_DIR_ENV})")
    if root.is_file():
        if root.suffix.lower() not in VIDEO_SUFFIXES:
            raise ImssrError(f"{root} is not a video ({', '.join(VIDEO_SUFFIXES)})")
        return (read_video(root, size, max_frames),)
    davis = root / "JPEGImages" / "480p"
    if davis.is_dir():
        root = davis
    clips: list[np.ndarray] = []
    for entry in sorted(root.iterdir()):
        if len(clips) >= max_clips:
            break
        if entry.is_dir():
            clips += _frame_folder(entry, size, max_frames)
        elif entry.suffix.lower() in VIDEO_SUFFIXES:
            clips.append(read_video(entry, size, max_frames))
    clips = clips or _frame_folder(root, size, max_frames)  # one folder of frames is one clip
    if not clips:
        raise ImssrError(f"no videos or frame folders under {root} (expected e.g. "
                         "DAVIS JPEGImages/480p/<video>/*.jpg or *.mp4 files)")
    return tuple(clips)


def footage_pool(size: int, split: str = "test", path: str = "") -> tuple[np.ndarray, ...]:
    """Clips for ``split``: from ``path`` / ``$IMSSR_FOOTAGE_DIR`` if given (several clips split
    alternately into train and test, a single clip serving both), else built in."""
    if split not in SPLITS:
        raise ImssrError(f"unknown footage split {split!r}; valid: {', '.join(SPLITS)}")
    source = path or os.environ.get(FOOTAGE_DIR_ENV, "")
    if not source:
        return builtin_footage(size, split)
    clips = load_footage(source, size)
    return clips if len(clips) == 1 else clips[SPLITS.index(split)::2]
