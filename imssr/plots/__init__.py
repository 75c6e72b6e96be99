"""Pictures of one run: its learning curve (``curves``), scene montages and episode videos
(``media``).  matplotlib and imageio are imported when a picture is drawn."""
from __future__ import annotations

from typing import Optional


def pyplot():
    """matplotlib's pyplot on the Agg backend (files only, no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def steps_axis(ax, action_repeat: Optional[int], frames: str = "frames", small: bool = False) -> None:
    """Agent steps on the x axis and, with an action repeat, environment frames on the top axis (frames = agent
    steps * action repeat), both as 250k, 4M (matplotlib's default puts a 1e6 offset over the title); ``small``:
    the top axis's label and ticks in a small font, for panels of a grid."""
    from matplotlib.ticker import EngFormatter

    ax.set_xlabel("agent steps")
    ax.xaxis.set_major_formatter(EngFormatter(sep=""))
    if action_repeat:
        top = ax.secondary_xaxis("top", functions=(lambda s: s * action_repeat, lambda f: f / action_repeat))
        top.set_xlabel(f"{frames} (action repeat {action_repeat})", **({"fontsize": 8} if small else {}))
        if small:
            top.tick_params(labelsize=7)
        top.xaxis.set_major_formatter(EngFormatter(sep=""))
