"""Reads back the history rows a W&B run wrote to its ``.wandb`` files.

W&B keeps each process's part of a run in ``offline-run-*-ID/run-ID.wandb`` (and ``run-*-ID``
online): W&B's header (``:W&B``, 2 bytes of magic, 1 of version) and then its records
(``wandb_internal_pb2.Record``) in LevelDB's log format (32 KiB blocks of chunks, each with a
4-byte checksum, a 2-byte length and a 1-byte type).  A process killed mid-write leaves a torn
last chunk, which ends the reading: what precedes it is what W&B holds.
"""
from __future__ import annotations

import glob
import json
import os
import re
import struct
from typing import Iterator

_HEADER = 7
_BLOCK = 32768
_FULL, _FIRST, _MIDDLE, _LAST = 1, 2, 3, 4


def _payloads(data: bytes) -> Iterator[bytes]:
    """The whole records of one ``.wandb`` file's bytes (chunks joined)."""
    if data[:4] != b":W&B":
        return
    pos, parts = _HEADER, []
    while pos + 7 <= len(data):
        left = _BLOCK - pos % _BLOCK
        if left < 7:  # a block's tail too short for a chunk header is padding
            pos += left
            continue
        length, kind = struct.unpack_from("<HB", data, pos + 4)
        if kind == 0 and length == 0:  # zeros: padding, or a file cut where it was preallocated
            pos += left
            continue
        body = data[pos + 7:pos + 7 + length]
        if len(body) < length:
            return
        pos += 7 + length
        if kind == _FULL:
            yield body
        elif kind == _FIRST:
            parts = [body]
        elif kind == _MIDDLE:
            parts.append(body)
        elif kind == _LAST:
            yield b"".join(parts + [body])
            parts = []
        else:
            return


def history_rows(path: str) -> list[dict]:
    """The history rows (``run.log`` calls) in the ``.wandb`` file ``path``, in the order logged."""
    from wandb.proto import wandb_internal_pb2

    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except OSError:
        return []
    rows = []
    for payload in _payloads(data):
        record = wandb_internal_pb2.Record()
        try:
            record.ParseFromString(payload)
        except Exception:  # noqa: BLE001 - a torn record ends what W&B holds
            break
        if record.WhichOneof("record_type") != "history":
            continue
        row = {}
        for item in record.history.item:
            # A picture's fields are nested under its key: the row holds the key.
            key = item.key or (item.nested_key[0] if item.nested_key else "")
            try:
                row[key] = json.loads(item.value_json)
            except ValueError:
                continue
        rows.append(row)
    return rows


def run_files(directory: str, run_id: str) -> list[str]:
    """The ``.wandb`` files of the W&B run ``run_id`` under ``directory`` (W&B's ``dir``), oldest first."""
    pattern = os.path.join(directory, "wandb", f"*run-*-{run_id}", f"run-{run_id}.wandb")
    # Directory names carry the process's start time (offline-run-20250101_120000-ID).
    return sorted(glob.glob(pattern), key=lambda p: re.findall(r"\d{8}_\d{6}", p)[-1:])


def logged_series(directory: str, run_id: str) -> set[tuple[str, int]]:
    """What the W&B run ``run_id`` written under ``directory`` holds: ``(prefix, frame)`` for each
    history row, its prefix the part of its keys before the last ``/`` (``train``,
    ``eval/training``; a row holds one prefix), or the whole key of a picture
    (``media/training_video``)."""
    held = set()
    for path in run_files(directory, run_id):
        for row in history_rows(path):
            frame = row.get("frame")
            if not isinstance(frame, (int, float)):
                continue
            for key in row:
                if "/" in key:
                    held.add((series_of(key), int(frame)))
    return held


def series_of(key: str) -> str:
    """The series a logged key belongs to (see :func:`logged_series`)."""
    return key if key.startswith("media/") else key.rsplit("/", 1)[0]
