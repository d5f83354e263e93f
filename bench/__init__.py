"""isobench's bench: plans cases × backends × methods × knobs, times, measures, reports, compares.

Entry point: ``python -m bench``.  Where things happen, top to bottom (each package imports only
from those below it; tests/test_import_cycles.py holds it):

* ``commands/`` — the command line: one module per command (its arguments and its ``run``);
  a new command is a new module there, found by ``python -m bench --help``;
* ``report/`` — reading a run: the report (one model rendered to Markdown and HTML), the first
  screen, ``compare``, how a run was spread;
* ``studies/`` — measurements beside the suites (speed, peers, sampling, extraction,
  stability), each a module with its measurement and its table; ``claims/`` — the lecture's
  claims, one module per claim;
* ``run/`` — running a plan: suites and plan, one configuration measured (timing, metrics,
  references, the backend contract), the executors (this process, a dask cluster), the results
  files, resume.
"""
