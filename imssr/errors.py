"""The one exception type that the CLI turns into a one-line error message."""


class ImssrError(Exception):
    """A user-facing error: bad input, missing file, corrupt checkpoint, missing library."""


class NonFiniteError(ImssrError):
    """A loss or signal became NaN or infinite during training."""


class DivergedError(NonFiniteError):
    """Training diverged: a loss or the agent's action is NaN or infinite
    ("diverged at agent step N: critic loss nan"); the last checkpoint is from before it."""
