"""Pictures of one run: its learning curve (``curves``), scene montages and episode videos
(``media``).  matplotlib and imageio are imported when a picture is drawn."""


def pyplot():
    """matplotlib's pyplot on the Agg backend (files only, no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
