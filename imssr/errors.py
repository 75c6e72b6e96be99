"""The one exception type that the CLI turns into a one-line error message, and the exit
statuses that other processes (the sweep) read."""

INTERRUPTED_EXIT = 130
"""Exit status of ``imssr train`` stopped by SIGTERM or SIGINT (Ctrl-C): it checkpointed where it
stopped (or, after a second signal, kept its last checkpoint) and ``--resume`` continues it.
128 + SIGINT, as a shell reports an interrupted command."""

DIVERGED_PREFIX = "diverged at agent step"
"""How a divergence's one-line error starts ("diverged at agent step N: critic loss nan")."""


class ImssrError(Exception):
    """A user-facing error: bad input, missing file, corrupt checkpoint, missing library."""


class NonFiniteError(ImssrError):
    """A loss or signal became NaN or infinite during training."""


class DivergedError(NonFiniteError):
    """Training diverged: a loss or the agent's action is NaN or infinite
    ("diverged at agent step N: critic loss nan"); the last checkpoint is from before it."""
