"""Embree (through embreex) as an engine backend: :mod:`impls.embree.backend`."""
