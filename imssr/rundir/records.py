"""A run's records of what it is: its resolved config (``config.json``) and its provenance
(``provenance.json``, a record per start and resume)."""
from __future__ import annotations

import json
import os
from typing import Optional

from imssr.config import RunConfig, load_config
from imssr.errors import ImssrError
from imssr.files import OWN_FILE_RULE, atomic_write_text
from imssr.jsonio import dumps
from imssr.rundir.layout import RunLayout


class Records(RunLayout):
    """The run's config and provenance records (a part of :class:`~imssr.rundir.RunDir`)."""

    def has_config(self) -> bool:
        return os.path.exists(self.config_path)

    def write_config(self, cfg: RunConfig) -> str:
        """Write the resolved config atomically (creating the directory)."""
        os.makedirs(self.path, exist_ok=True)
        atomic_write_text(self.config_path, cfg.to_json() + "\n")
        return self.config_path

    def read_config(self) -> RunConfig:
        """The run's config (a one-line error when it is missing or invalid)."""
        return load_config(self.config_path)

    def record_provenance(self, record: dict) -> str:
        """Append ``record`` (:func:`imssr.provenance.record`) to the run's provenance, atomically.
        A file that cannot be read is kept beside as ``provenance.json.damaged`` and a new list
        begun; a symbolic link in its place is refused (:meth:`refuse_linked_provenance`)."""
        self.refuse_linked_provenance()
        records = self.read_provenance()
        if records is None:
            os.replace(self.provenance_path, self.provenance_path + ".damaged")
            records = []
        os.makedirs(self.path, exist_ok=True)
        atomic_write_text(self.provenance_path, dumps({"records": records + [record]}, indent=2) + "\n")
        return self.provenance_path

    def refuse_linked_provenance(self) -> None:
        """A one-line error when ``provenance.json`` is a symbolic link: the records are read back
        and rewritten whole at every start, so through a link they would take in a file from
        outside the run (or set that file aside as damaged), as a log written through one would
        (:func:`~imssr.files.open_own`)."""
        if os.path.islink(self.provenance_path):
            raise ImssrError(f"{self.provenance_path} is a symbolic link; {OWN_FILE_RULE}")

    def read_provenance(self) -> Optional[list[dict]]:
        """The provenance records, oldest first: [] when there is no file (a run of imssr before
        them), None when the file cannot be read."""
        if not os.path.exists(self.provenance_path):
            return []
        data = read_json(self.provenance_path)
        records = data.get("records") if isinstance(data, dict) else None
        if not isinstance(records, list) or not all(isinstance(r, dict) for r in records):
            return None
        return records


def read_json(path: str) -> Optional[dict]:
    """The JSON object in ``path``; None when it is missing, unreadable or not an object."""
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except (OSError, ValueError, RecursionError):  # ValueError: bad JSON or not UTF-8
        return None
    return data if isinstance(data, dict) else None
