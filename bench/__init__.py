"""isobench runner: plans cases × backends × methods × knobs, times, measures, reports, compares.

Entry point: ``python -m bench`` (see ``bench/commands/cli.py``).
"""
