"""``imssr sweep``: a grid of runs (``grid``), each an ``imssr train`` subprocess on a worker
(``runner``), dispatched through Ray with resume, retries and a status file (``sweep``).
Ray is the ``sweep`` extra (``pip install 'imssr[sweep]'``), imported only to dispatch."""
