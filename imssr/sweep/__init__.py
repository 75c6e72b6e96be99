"""``imssr sweep``: a grid of runs (``grid``), each an ``imssr train`` subprocess (``runner``)
started by a launcher (``launchers``: Ray, SLURM or local subprocesses) and dispatched with
resume, retries and a status file (``sweep``) in the sweep root (``directory``)."""
