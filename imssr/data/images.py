"""Pools of natural images for random overlay (SODA) and, later, distracting scenes.

Two sources: a user-supplied folder (any tree of ``.jpg`` / ``.jpeg`` / ``.png``, e.g. a Places365 download, as
``aux.image_dir`` or ``$IMSSR_IMAGE_DIR``), else the photographs that installed packages ship, cut into square
patches at random positions and scales (nothing is downloaded).  A pool is a uint8 array ``(N, 3, size, size)``,
cached per process.
"""
from __future__ import annotations

import functools
import importlib.util
import os
from pathlib import Path
from typing import Optional

import numpy as np
from PIL import Image

from imssr.errors import ImssrError

IMAGE_DIR_ENV = "IMSSR_IMAGE_DIR"
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")

# Pictures that installed packages ship, as (package, path inside it), in three
# disjoint roles so that nothing an agent sees while training (overlay images,
# training footage) reappears in test footage.  Synthetic or document images
# (text, chessboard, page, ...) are never used: the overlay should look like the
# natural scenes of Places365.  Every labmaze sky box stays within one role.
SOURCES = {
    "overlay": (("skimage", "data/coffee.png"), ("skimage", "data/rocket.jpg"),
                ("skimage", "data/retina.jpg"), ("skimage", "data/ihc.png"),
                ("skimage", "data/brick.png"), ("sklearn", "datasets/images/china.jpg"),
                ("matplotlib", "mpl-data/sample_data/grace_hopper.jpg")),
    "footage_train": (("skimage", "data/chelsea.png"), ("skimage", "data/motorcycle_left.png"),
                      ("skimage", "data/gravel.png"),
                      *(("labmaze", f"assets/sky_01/{f}.png") for f in ("ft", "lf", "rt", "bk"))),
    "footage_test": (("skimage", "data/astronaut.png"), ("skimage", "data/hubble_deep_field.jpg"),
                     ("skimage", "data/grass.png"), ("sklearn", "datasets/images/flower.jpg"),
                     *(("labmaze", f"assets/sky_0{i}/{f}.png") for i in (2, 3) for f in ("ft", "lf"))),
}


def source_files(role: str) -> list[Path]:
    """Installed pictures for ``role`` (overlay, footage_train, footage_test); missing ones are skipped."""
    found = []
    for package, relative in SOURCES[role]:
        spec = importlib.util.find_spec(package)
        if spec is not None and spec.submodule_search_locations:
            path = Path(list(spec.submodule_search_locations)[0]) / relative
            if path.is_file():
                found.append(path)
    return found


def _read_rgb(path: Path):
    try:
        with Image.open(path) as im:
            return im.convert("RGB")
    # PIL raises SyntaxError for some broken files and DecompressionBombError for huge ones.
    except (OSError, ValueError, SyntaxError, EOFError, Image.DecompressionBombError) as exc:
        raise ImssrError(f"cannot read image {path}: {exc}") from None


def _square_resize(image, size: int, box: Optional[tuple[int, int, int, int]] = None) -> np.ndarray:
    if box is None:  # centre square
        w, h = image.size
        s = min(w, h)
        box = ((w - s) // 2, (h - s) // 2, (w - s) // 2 + s, (h - s) // 2 + s)
    patch = image.resize((size, size), Image.BILINEAR, box=box)
    return np.asarray(patch, dtype=np.uint8).transpose(2, 0, 1)


@functools.lru_cache(maxsize=8)
def builtin_photographs(size: int, count: int = 512, seed: int = 0) -> np.ndarray:
    """``count`` square patches (random position, 30-100% of the short side) of the shipped
    overlay photographs (never used for footage)."""
    files = source_files("overlay")
    if not files:
        raise ImssrError("no built-in photographs found (install scikit-image); "
                         f"or point aux.image_dir / ${IMAGE_DIR_ENV} at a folder of jpg/png images")
    images = [_read_rgb(p) for p in files]
    rng = np.random.default_rng(seed)
    out = np.empty((count, 3, size, size), dtype=np.uint8)
    for i in range(count):
        im = images[i % len(images)]
        w, h = im.size
        s = int(min(w, h) * rng.uniform(0.3, 1.0))
        x, y = int(rng.integers(0, w - s + 1)), int(rng.integers(0, h - s + 1))
        patch = _square_resize(im, size, (x, y, x + s, y + s))
        out[i] = patch[:, :, ::-1] if rng.random() < 0.5 else patch  # horizontal flip
    return out


def _image_files(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())


@functools.lru_cache(maxsize=8)
def load_image_folder(path: str, size: int, max_images: int = 1024, seed: int = 0) -> np.ndarray:
    """Up to ``max_images`` images under ``path`` (recursively), centre-square resized to
    ``size``; a larger folder is subsampled with ``seed``.  An unreadable file is skipped (and
    replaced by another drawn with the same seed), counted in one warning line."""
    root = Path(path).expanduser()
    if not root.exists():
        raise ImssrError(f"image folder not found: {root} (aux.image_dir or ${IMAGE_DIR_ENV})")
    if not root.is_dir():
        raise ImssrError(f"image folder is not a directory: {root}")
    files = _image_files(root)
    if not files:
        raise ImssrError(f"no .jpg/.jpeg/.png images under {root}")
    order: list[int] = list(range(len(files)))
    if len(files) > max_images:
        # The first max_images drawn are the pool; the rest, in a seeded order, replace
        # unreadable ones, so a folder without bad files gives the same pool either way.
        rng = np.random.default_rng(seed)
        pick = sorted(rng.choice(len(files), max_images, replace=False))
        rest = sorted(set(range(len(files))) - set(pick))
        order = pick + [rest[j] for j in rng.permutation(len(rest))]
    pool, tried = [], 0
    for i in order:
        if len(pool) == max_images:
            break
        tried += 1
        try:
            pool.append(_square_resize(_read_rgb(files[i]), size))
        except ImssrError:
            continue
    skipped = tried - len(pool)
    if not pool:
        raise ImssrError(f"no readable images under {root}: all {skipped:,} .jpg/.jpeg/.png files failed to load")
    if skipped:
        print(f"imssr: warning: skipped {skipped:,} of {tried:,} unreadable images in {root}", flush=True)
    return np.stack(pool)


def image_pool(size: int, image_dir: str = "", max_images: int = 1024) -> np.ndarray:
    """The overlay pool: ``image_dir``, else ``$IMSSR_IMAGE_DIR``, else the built-in photographs."""
    folder = image_dir or os.environ.get(IMAGE_DIR_ENV, "")
    return load_image_folder(folder, size, max_images) if folder else builtin_photographs(size, min(max_images, 512))
