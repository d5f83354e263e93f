"""Warp backend (a plug-in): :mod:`impls.warp.backend`."""
