"""``imssr sweep``: a grid of runs (``grid``), each an ``imssr train`` subprocess on a worker
(``runner``), started by a launcher (``launchers``: Ray, SLURM or local subprocesses) and
dispatched with resume, retries and a status file (``sweep``); the sweep root's own files are
``directory``'s.  Ray is the ``sweep`` extra (``pip install 'imssr[sweep]'``), imported only to
dispatch."""
