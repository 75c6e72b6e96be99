"""Small shared helpers: atomic files and the thread-contention warning."""
import os

import pytest

from imssr.utils import atomic_path, atomic_write_csv, atomic_write_text, contention_warning


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


@pytest.mark.parametrize("threads, load, cores, warns", [
    (2, 0.1, 2, False),   # idle machine: both threads have a core
    (2, 1.0, 2, True),    # another job holds a core
    (2, 2.3, 2, True),    # e.g. a test suite beside the run
    (1, 5.0, 2, False),   # one thread never spins against itself
    (4, 1.0, 8, False),   # plenty of free cores
])
def test_contention_warning(threads, load, cores, warns):
    message = contention_warning(threads, load=load, cores=cores)
    assert (message is not None) == warns
    if warns:
        assert "\n" not in message and "train.torch_threads=1" in message
