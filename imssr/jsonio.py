"""JSON that every reader accepts: no bare ``NaN`` / ``Infinity`` in the files imssr writes.

Python's :mod:`json` writes non-finite floats as ``NaN`` and ``Infinity``, which are not JSON
(``jq``, JavaScript and strict parsers refuse them).  :func:`dumps` writes them as ``null``
and refuses anything else that would not be JSON (``allow_nan=False``).
"""
from __future__ import annotations

import json
import math
from typing import Any


def finite(obj: Any) -> Any:
    """``obj`` with every non-finite float (in dicts, lists and tuples, at any depth) as None."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    return obj


def dumps(obj: Any, **kwargs) -> str:
    """:func:`json.dumps` with non-finite floats as ``null`` (strict JSON)."""
    return json.dumps(finite(obj), allow_nan=False, **kwargs)
