"""The ``imssr`` command's entry point (``python -m imssr`` too).

It loads the command-line interface, which takes seconds to import (torch, dm_control), inside a guard: a Ctrl-C in
those seconds is one line and exit status 130, not a traceback.
"""
from __future__ import annotations

import sys
from typing import Optional

from imssr.crash import report_native_crashes
from imssr.errors import INTERRUPTED_EXIT
from imssr.memlimit import calm_openblas


def main(argv: Optional[list[str]] = None) -> int:
    calm_openblas()  # before anything loads scipy (a sweep's runs inherit it)
    report_native_crashes()
    try:
        from imssr.cli import main as cli_main
    except KeyboardInterrupt:
        print("imssr: interrupted while starting; nothing was run", file=sys.stderr)
        return INTERRUPTED_EXIT
    return cli_main(argv)
