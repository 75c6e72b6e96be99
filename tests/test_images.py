"""Natural-image pools: a user folder, the built-in photographs, clear errors."""
import numpy as np
import pytest
from PIL import Image

from conftest import image_folder
from imssr.data import IMAGE_DIR_ENV, builtin_photographs, image_pool, load_image_folder
from imssr.errors import ImssrError


def test_folder_loader_reads_a_tree_of_jpg_and_png(tmp_path):
    image_folder(tmp_path)
    pool = load_image_folder(str(tmp_path), 16)
    assert pool.shape == (5, 3, 16, 16) and pool.dtype == np.uint8
    assert pool.std() > 10  # real content, not a constant fill
    sub = load_image_folder(str(tmp_path), 16, max_images=3)
    assert sub.shape == (3, 3, 16, 16)


def test_folder_errors_are_one_line(tmp_path):
    with pytest.raises(ImssrError, match="image folder not found"):
        load_image_folder(str(tmp_path / "missing"), 16)
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "readme.txt").write_text("x")
    with pytest.raises(ImssrError, match="no .jpg/.jpeg/.png images"):
        load_image_folder(str(tmp_path / "empty"), 16)


def test_environment_variable_selects_the_folder(tmp_path, monkeypatch):
    image_folder(tmp_path, n=3)
    monkeypatch.setenv(IMAGE_DIR_ENV, str(tmp_path))
    assert image_pool(12).shape == (3, 3, 12, 12)
    monkeypatch.delenv(IMAGE_DIR_ENV)
    assert image_pool(12).shape[0] > 100  # built-in pool


def test_builtin_pool_is_made_of_varied_colour_photographs():
    pool = builtin_photographs(32, count=64)
    assert pool.shape == (64, 3, 32, 32) and pool.dtype == np.uint8
    assert len({p.tobytes() for p in pool}) == 64  # distinct patches
    colour = np.abs(pool[:, 0].astype(int) - pool[:, 2].astype(int)).mean()
    assert colour > 5  # not grey-scale
    assert np.array_equal(pool, builtin_photographs(32, count=64))  # deterministic


def _spoil(root, names):
    """Files with image names that no decoder reads: garbage bytes, a truncated PNG, an empty file."""
    import io

    png = io.BytesIO()
    Image.fromarray(np.full((40, 40, 3), 128, np.uint8)).save(png, format="PNG")
    for i, name in enumerate(names):
        path = root / "bad" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if i % 3 == 0:
            path.write_bytes(b"\x00garbage" * 50)
        elif i % 3 == 1:
            path.write_bytes(png.getvalue()[:60])
        else:
            path.write_bytes(b"")


def test_unreadable_images_are_skipped_with_a_count(tmp_path, capsys):
    image_folder(tmp_path, n=5)
    _spoil(tmp_path, ["a.jpg", "b.png", "c.jpeg"])
    pool = load_image_folder(str(tmp_path), 16)
    assert pool.shape == (5, 3, 16, 16)
    assert capsys.readouterr().out.strip() == f"imssr: warning: skipped 3 of 8 unreadable images in {tmp_path}"
    # A subsampled folder replaces an unreadable pick by another image: the pool keeps its size.
    for seed in range(4):
        assert load_image_folder(str(tmp_path), 12, max_images=4, seed=seed).shape == (4, 3, 12, 12)
    # Without bad files the subsample is what it always was (the pool is rebuilt on resume).
    from imssr.data.images import _image_files, _read_rgb, _square_resize

    clean = tmp_path / "clean"
    image_folder(clean, n=6)
    files = _image_files(clean)
    pick = sorted(np.random.default_rng(0).choice(len(files), 3, replace=False))
    before = np.stack([_square_resize(_read_rgb(files[i]), 12) for i in pick])
    assert np.array_equal(load_image_folder(str(clean), 12, max_images=3), before)


def test_a_folder_without_one_readable_image_is_a_one_line_error(tmp_path):
    _spoil(tmp_path, ["a.jpg", "b.png", "c.jpeg", "d.jpg"])
    with pytest.raises(ImssrError, match=r"no readable images under .*: all 4 .jpg/.jpeg/.png files failed to load"):
        load_image_folder(str(tmp_path), 16)
