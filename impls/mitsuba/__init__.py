"""Mitsuba 3 backend (a plug-in): :mod:`impls.mitsuba.backend`."""
