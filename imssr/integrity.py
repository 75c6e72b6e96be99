"""Checksums of the files a run depends on: checkpoints and replay buffers.

A zip file (a torch checkpoint, a numpy ``.npz``) is *sealed* by writing the sha256 of its bytes into the zip archive
comment, the field that ends every zip file: still a plain zip for ``torch.load`` and ``np.load``, and the atomic
rename that publishes the file publishes its checksum with it.  The digest covers every byte up to the comment-length
field, then that field as zero.  Every checkpoint and replay index imssr writes is sealed, so a file without a seal
where the file ends (cut short, extended, or never sealed) is not trusted.
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
    """A write-only file object that passes writes on to ``fh``: ``digest`` (with ``hashing``)
    is the sha256 of the bytes written, in order; ``error`` the first ``OSError`` of a write,
    which torch's zip writer replaces with a ``RuntimeError`` of its own ("unexpected pos")."""

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
    """Write the sha256 of the zip file at ``path`` (ending with a directory record without
    comment, as torch and numpy write them) into its archive comment; return the digest."""
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


MISMATCH = "checksum mismatch"
""":func:`zip_seal_problem`: the file's bytes do not match its seal."""
DISPLACED = "its checksum is not at its end: cut short or extended"
""":func:`zip_seal_problem`: a seal near the file's end, but not where the file ends."""
UNSEALED = "no checksum"
""":func:`zip_seal_problem`: no seal at all (a file imssr did not write, or not a zip)."""
_SEARCH = (1 << 16) + _EOCD_LEN + _COMMENT_LEN  # as far back as a zip reader looks for its directory


def zip_seal_problem(path: str) -> Optional[str]:
    """None when the file at ``path`` ends with a seal that matches its bytes; else why it cannot be trusted:
    :data:`MISMATCH`, :data:`DISPLACED` or :data:`UNSEALED`.  ``OSError`` when the file cannot be read."""
    with open(path, "rb") as fh:
        size = fh.seek(0, 2)
        tail_len = _EOCD_LEN + _COMMENT_LEN
        if size >= tail_len:
            fh.seek(size - tail_len)
            tail = fh.read(tail_len)
            if _is_seal_record(tail) and len(tail) == tail_len:
                h = sha256_of(fh, size - _COMMENT_LEN - 2)
                h.update(b"\0\0")
                return None if h.hexdigest().encode() == tail[22 + len(SEAL_TAG):] else MISMATCH
        fh.seek(max(0, size - _SEARCH))
        data = fh.read()
    pos = data.rfind(_EOCD)
    while pos >= 0:
        if _is_seal_record(data[pos:]):
            return DISPLACED
        pos = data.rfind(_EOCD, 0, pos)
    return UNSEALED


def _is_seal_record(data: bytes) -> bool:
    """``data`` starts with an end-of-central-directory record whose comment is a seal, as far as
    ``data`` reaches (a file cut inside its seal keeps the seal's start)."""
    if len(data) < _EOCD_LEN or data[:4] != _EOCD or data[20:22] != struct.pack("<H", _COMMENT_LEN):
        return False
    start = data[22:22 + len(SEAL_TAG)]
    return start == SEAL_TAG[:len(start)]
