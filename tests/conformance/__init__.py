"""The backend conformance suite, generated from the method catalog and the capabilities table.

Every registered backend (built-ins, entry points, and any ``--backend module:attr`` plug-in via
``ISOBENCH_EXTRA_BACKENDS``) is checked, method × applicable scene, against exact answers in
float64.  A backend's known failures come from ``Capabilities.expected_failures`` (one place,
with reasons) and are marked ``xfail(strict=True)``.

The test scenes are small :class:`reference.Field` subclasses with exact answers (until the
reference catalog's wider scenes land): an off-centre sphere (exact SDF), a union of two
spheres (a distance bound, not an SDF), and the lecture's algebraic sphere |x − c|² − r²
(not an SDF: Δφ = 6 while κ1 + κ2 = 2/r).

One file per kind of check (root finders, the ray-bounds clip, gradients, renderers, every method
of the catalog, engines; the scenes and helpers in ``common.py``, the backends in ``conftest.py``),
so that ``pytest -n auto --dist loadfile``, which runs a file whole on one worker, spreads the
suite over the workers (as one file it was the longest unit of the test run but one).
"""
