"""Checksums of the files a run depends on: checkpoints and replay buffers.

A zip file (a torch checkpoint, a numpy ``.npz``) is *sealed* by writing the sha256 of its
bytes into the zip archive comment, the field that ends every zip file.  A sealed file is
still a plain zip: ``torch.load`` and ``np.load`` read it as before, and the checksum travels
inside the file, so the atomic rename that publishes the file publishes its checksum with it
(no kill can leave a file and a checksum of another version side by side, and a reader never
sees one without the other).  The digest covers the file as it was written, before the seal:
every byte up to the comment-length field, then that field as zero.

Files written before checksums existed have no seal and are read unverified.
"""
from __future__ import annotations

import hashlib
import struct
from typing import BinaryIO, Optional

SEAL_TAG = b"imssr-sha256:"
_DIGEST_HEX = 64
_COMMENT_LEN = len(SEAL_TAG) + _DIGEST_HEX
_EOCD = b"PK\x05\x06"  # end-of-central-directory record: 22 bytes, then the comment
_EOCD_LEN = 22
CHUNK = 1 << 22


class HashingWriter:
    """A write-only file object that passes writes on to ``fh`` and keeps what they did.

    ``digest`` (with ``hashing``) is the sha256 of the bytes written, in order (for writers
    that only append, e.g. ``np.save``).  ``error`` is the first ``OSError`` of a write:
    torch's zip writer replaces it with a ``RuntimeError`` of its own ("unexpected pos"), so
    the caller re-raises the real cause (a full disk) from here.
    """

    def __init__(self, fh: BinaryIO, hashing: bool = True):
        self.fh = fh
        self.hash = hashlib.sha256() if hashing else None
        self.error: Optional[OSError] = None
        self.nbytes = 0

    def write(self, data) -> int:
        try:
            n = self.fh.write(data)
        except OSError as exc:
            self.error = self.error or exc
            raise
        if self.hash is not None:
            self.hash.update(data)
        self.nbytes += memoryview(data).nbytes
        return n

    def flush(self) -> None:
        self.fh.flush()

    @property
    def digest(self) -> str:
        assert self.hash is not None
        return self.hash.hexdigest()


def sha256_of(fh: BinaryIO, size: int) -> "hashlib._Hash":
    """sha256 of the first ``size`` bytes of ``fh`` (from its start), streamed."""
    h = hashlib.sha256()
    fh.seek(0)
    left = size
    while left > 0:
        block = fh.read(min(CHUNK, left))
        if not block:
            break
        h.update(block)
        left -= len(block)
    return h


def seal_zip(path: str) -> str:
    """Write the sha256 of the zip file at ``path`` into its archive comment; return the digest.

    The file must end with an end-of-central-directory record without comment, as torch and
    numpy write them.
    """
    with open(path, "rb+") as fh:
        size = fh.seek(0, 2)
        if size >= _EOCD_LEN:
            fh.seek(size - _EOCD_LEN)
            eocd = fh.read(_EOCD_LEN)
        if size < _EOCD_LEN or eocd[:4] != _EOCD or eocd[20:] != b"\0\0":
            raise ValueError(f"{path} does not end with a zip directory without comment")
        digest = sha256_of(fh, size).hexdigest()
        fh.seek(size - 2)
        fh.write(struct.pack("<H", _COMMENT_LEN) + SEAL_TAG + digest.encode())
    return digest


def check_zip(path: str) -> Optional[bool]:
    """True when the file's seal matches its bytes, False when it does not (the file is
    damaged), None when the file carries no seal (written before checksums, or not a zip)."""
    with open(path, "rb") as fh:
        size = fh.seek(0, 2)
        tail_len = _EOCD_LEN + _COMMENT_LEN
        if size < tail_len:
            return None
        fh.seek(size - tail_len)
        tail = fh.read(tail_len)
        if (tail[:4] != _EOCD or tail[20:22] != struct.pack("<H", _COMMENT_LEN)
                or tail[22:22 + len(SEAL_TAG)] != SEAL_TAG):
            return None
        stored = tail[22 + len(SEAL_TAG):]
        h = sha256_of(fh, size - _COMMENT_LEN - 2)
        h.update(b"\0\0")
        return h.hexdigest().encode() == stored
