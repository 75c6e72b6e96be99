"""Seals (:mod:`imssr.integrity`): a zip file is trusted only when it ends with a seal that matches
its bytes; a seal that is no longer where the file ends (cut short, or bytes appended) and a file
without one are told apart from a match."""
import zipfile

import pytest

from imssr.integrity import DISPLACED, MISMATCH, UNSEALED, seal_zip, zip_seal_problem


def _flip_middle(data: bytes) -> bytes:
    mid = len(data) // 2
    return data[:mid] + bytes([data[mid] ^ 0xFF]) + data[mid + 1:]


@pytest.fixture
def sealed(tmp_path):
    path = tmp_path / "a.zip"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("data", bytes(range(256)) * 8)
    seal_zip(str(path))
    return path


@pytest.mark.parametrize("change, problem", [
    (lambda b: b, None),
    (_flip_middle, MISMATCH),
    (lambda b: b[:-1], DISPLACED),  # cut inside the digest: a zip reader still opens it
    (lambda b: _flip_middle(b)[:-1], DISPLACED),
    (lambda b: b[:-70], DISPLACED),  # cut inside the seal's tag
    (lambda b: b + b"\0", DISPLACED),  # a byte appended
    (lambda b: b + bytes(70_000), UNSEALED),  # appended past where a zip reader looks for its end
    (lambda b: b[:len(b) // 2], UNSEALED),  # nothing of the seal left
    (lambda b: b"", UNSEALED),
])
def test_a_seal_tells_what_happened_to_its_file(sealed, change, problem):
    sealed.write_bytes(change(sealed.read_bytes()))
    assert zip_seal_problem(str(sealed)) == problem


def test_a_zip_without_a_seal_and_a_file_that_is_no_zip_are_unsealed(tmp_path):
    plain = tmp_path / "plain.zip"
    with zipfile.ZipFile(plain, "w") as archive:
        archive.writestr("data", b"x")
    text = tmp_path / "text"
    text.write_text("hello world\n")
    assert zip_seal_problem(str(plain)) == zip_seal_problem(str(text)) == UNSEALED
