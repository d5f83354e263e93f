"""Running a plan: choose the configurations (suites, plan), measure each one (timing, metrics,
references), execute them in this process or on a dask cluster, and record the rows (results,
the run directory's lock, resume).  Builds on :mod:`impls` and :mod:`reference` only."""
