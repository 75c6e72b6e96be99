"""JSON that every reader accepts: non-finite floats written as ``null`` (Python's ``NaN`` and ``Infinity`` are not
JSON: ``jq`` and strict parsers refuse them), and JSON files read back with one-line errors.
"""
from __future__ import annotations

import json
import math
from typing import Any, Optional

from imssr.errors import ImssrError


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


def read_json(path: str, what: str, kind: Optional[str] = None) -> Any:
    """The JSON value of the file ``path``; a missing file, a folder and anything that is not JSON
    text are one-line errors that name the file as ``what`` ("config file") and, for JSON nested
    too deeply to mean anything, say it cannot be a ``kind`` (default: ``what``)."""
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except FileNotFoundError:
        raise ImssrError(f"{what} not found: {path}") from None
    except IsADirectoryError:
        raise ImssrError(f"{what} {path} is a directory") from None
    except UnicodeDecodeError:
        raise ImssrError(f"{what} {path} is not a JSON text file (it is not UTF-8 text)") from None
    except json.JSONDecodeError as exc:
        raise ImssrError(f"{what} {path} is not valid JSON: {exc}") from None
    except RecursionError:
        raise ImssrError(f"{what} {path} nests its JSON too deeply to be a {kind or what}") from None
