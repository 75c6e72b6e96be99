"""The config format's version: the one this imssr reads and writes, and the refusal of others.

``CONFIG_VERSION`` 2 is the format with budgets in agent steps; imssr 0.1's configs
(version 1: budgets in frames) are refused in one line (:func:`check_version`).
"""
from __future__ import annotations

from typing import Any

from imssr.errors import ImssrError

CONFIG_VERSION = 2
"""The config format this imssr reads and writes: budgets in agent steps.  Version 1, imssr 0.1's
(budgets in frames, no ``version`` key), is refused: CHANGELOG.md, 0.2.0, says what its runs need."""
V1_KEYS = (("train", "frames"), ("train", "eval_every_frames"), ("train", "checkpoint_every_frames"),
            ("intrinsic", "view"))
"""Keys only imssr 0.1's configs hold: a file with one of them and no ``version`` is one of those."""


def check_version(data: dict[str, Any], source: str = "this config") -> None:
    """Refuse, in one line, a config dict of another format than :data:`CONFIG_VERSION`: imssr
    0.1's (``version`` 1, or none and a key of :data:`V1_KEYS`), or an unknown version.  A dict
    without ``version`` and without those keys is a partial config written by hand for this one."""
    version = data.get("version")
    if version is None and any(isinstance(data.get(section), dict) and key in data[section]
                               for section, key in V1_KEYS):
        version = 1
    if version == 1 and not isinstance(version, bool):
        raise ImssrError(f"{source} is an imssr 0.1 config (budgets in frames), which this imssr does not "
                         "read: re-run the run, or evaluate it with imssr 0.1 (CHANGELOG.md, 0.2.0)")
    if version is not None and (version != CONFIG_VERSION or isinstance(version, bool)):
        raise ImssrError(f"{source} has config version {version!r}; this imssr reads version {CONFIG_VERSION}")
