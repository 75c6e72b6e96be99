"""imssr.files: files written whole or not at all."""
import os

import pytest

from imssr.files import atomic_path, atomic_write_csv, atomic_write_text


def test_atomic_write_replaces_whole_file(tmp_path):
    path = tmp_path / "sub" / "f.txt"
    atomic_write_text(str(path), "old\n")
    atomic_write_text(str(path), "new\n")
    assert path.read_text() == "new\n"
    assert os.listdir(path.parent) == ["f.txt"]  # no temporary file left behind


def test_atomic_path_keeps_old_file_when_writer_fails(tmp_path):
    path = tmp_path / "f.txt"
    path.write_text("old\n")
    with pytest.raises(RuntimeError):
        with atomic_path(str(path)) as tmp:
            with open(tmp, "w") as fh:
                fh.write("half")
            raise RuntimeError("killed mid-write")
    assert path.read_text() == "old\n"
    assert os.listdir(tmp_path) == ["f.txt"]


def test_atomic_write_csv(tmp_path):
    path = tmp_path / "t.csv"
    atomic_write_csv(str(path), ["a", "b"], [[1, 2], [3, 4]])
    assert path.read_text().splitlines() == ["a,b", "1,2", "3,4"]
