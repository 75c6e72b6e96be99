"""``imssr report``: a sweep directory read back (``results``), the paper's tables (``tables``), rliable aggregates
(``aggregate``), figures (``figures``) and the whole report (``report``)."""
