"""Pictures of one run: its learning curve (``curves``), scene montages and episode videos
(``media``).  matplotlib and imageio are imported when a picture is drawn."""
