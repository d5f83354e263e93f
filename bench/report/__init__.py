"""Reading a run: the report (markdown and HTML), the first screen, the comparison of two runs
and how a run was spread over processes.  Reads what :mod:`bench.run` wrote."""
