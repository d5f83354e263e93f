"""numba backend (plug-in): per-ray compiled root finders on compiled scene trees (``backend.py``)."""
