"""Studies beside the suites, each with its own question and table: speed (throughput on 2^20
rays), peers (outside implementations), sampling (samples per ray to a colour error), extraction
(marching cubes against the exact surface) and stability (root finders on adversarial rays).

A new study is a module here (its measurement and its table) and a command module in
:mod:`bench.commands` that runs it; a study builds on :mod:`bench.run`, never on a command or
the report."""
