"""``imssr report``: a sweep directory read back (``results``), the paper's tables
(``tables``), rliable aggregates (``aggregate``), figures (``figures``) and the whole report
(``report``).  rliable (and the pandas it needs) is the ``report`` extra
(``pip install 'imssr[report]'``), imported only where an IQM is computed (at least 5 seeds per task)."""
