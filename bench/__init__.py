"""isobench runner: plans cases × backends × methods × knobs, times, measures, reports, compares.

Entry point: ``python -m bench`` (one module per command in ``bench/commands/``).
"""
