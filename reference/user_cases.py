"""Cases from outside the repository: a user's scene and rays benchmarked like the built-in ones.

Two ways in, as for backends:

* ``--cases my_pkg.my_module:attr`` on ``python -m bench run`` / ``cases`` (:func:`load`);
* an entry point in the group ``isobench.cases`` of an installed package
  (``my_cases = "my_pkg.my_module:attr"``; :func:`load_entry_points`).

``attr`` is a :class:`reference.cases.Case`, an iterable of them, or a callable with no
arguments returning either.  A user's case is untrusted input: each is validated
(:func:`validate`) and registered in the one catalog under its own id, tagged ``user``, so
tests, ``bench`` and reports treat it as any other case; a clash with an existing id is an
error naming both.  Its exact answers come from the case itself as for every case: closed forms
when its scene states ``exact_hits``, else the certified numerical reference
(:mod:`reference.numerical`), which needs a Lipschitz bound.

Example (``my_cases.py`` on the ``PYTHONPATH``)::

    import numpy as np
    from reference import Case, CallableField, rays

    def blob(x, xp):
        return xp.sqrt(xp.sum(x * x, axis=-1)) - 1.0 + 0.1 * xp.sin(4 * x[..., 0])

    o, d = rays.pinhole(eye=(0, 0, 3), look_at=(0, 0, 0), up=(0, 1, 0), fov_deg=40, width=16, height=16)
    CASES = [Case(id="user.blob.camera", scene=CallableField(blob, lipschitz=1.4, name="my_cases.blob", smooth=True),
                  origins=o, directions=d, t_min=0.0, t_max=6.0)]

then ``python -m bench run --cases my_cases:CASES --case 'user.*'``.  ``smooth=True`` (the blob is
C²) also runs the normal and curvature methods on it, judged against jax's autodiff of ``blob``
(:mod:`reference.autodiff`); with ``params=(1.0, 0.1)`` and ``blob(x, xp, theta)`` using
``theta[0]`` and ``theta[1]`` for the radius and the ripple, the dt/dθ methods too.
"""

from __future__ import annotations

import dataclasses
import importlib
import numbers
import re
from importlib import metadata

import numpy as np

from . import cases as _cases
from .cases import Case
from .rays import unit_tolerance

ENTRY_POINT_GROUP = "isobench.cases"
_ID = re.compile(r"^[A-Za-z0-9_\-]+(\.[A-Za-z0-9_\-+]+)+$")


def validate(case, source: str) -> Case:
    """``case`` checked as a catalog entry (ValueError/TypeError naming ``source`` and the fix):
    a :class:`Case` with a dotted id, float64-convertible finite ``(n, 3)`` origins and unit
    directions, t_min < t_max, a scene with ``value`` and ``info``.  Returns it with the tag
    ``user`` added."""
    if not isinstance(case, Case):
        raise TypeError(f"{source}: expected reference.cases.Case objects, got {type(case).__name__}; build them "
                        "with Case(id=..., scene=..., origins=..., directions=...)")
    if not isinstance(case.id, str) or not _ID.match(case.id):
        raise ValueError(f"{source}: case id {case.id!r} must be dotted words like 'user.blob.camera'")
    o = np.asarray(case.origins, dtype=np.float64)
    d = np.asarray(case.directions, dtype=np.float64)
    for name, a in (("origins", o), ("directions", d)):
        if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] == 0:
            raise ValueError(f"{source}: case {case.id!r} {name} must have shape (n, 3) with n ≥ 1, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{source}: case {case.id!r} has non-finite {name}")
    if o.shape != d.shape:
        raise ValueError(f"{source}: case {case.id!r} has {o.shape[0]} origins but {d.shape[0]} directions")
    # the backends' and the numerical reference's tolerance (reference.rays.unit_tolerance): a case
    # accepted at 1e-12 had every configuration refused by the backends and no numerical truth
    off, tol = float(np.max(np.abs(np.linalg.norm(d, axis=1) - 1.0))), unit_tolerance(np.float64)
    if off > tol:
        raise ValueError(f"{source}: case {case.id!r} directions must be unit vectors to float64's rounding "
                         f"(|‖d‖ − 1| ≤ {tol:.1e}; worst is {off:.2g} off); "
                         "normalise them in float64 (d / np.linalg.norm(d, axis=1, keepdims=True))")
    for name in ("t_min", "t_max"):
        v = getattr(case, name)
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real):
            raise TypeError(f"{source}: case {case.id!r} {name} must be a real number (depth along the ray), got "
                            f"{type(v).__name__} {v!r}")
    if not (float(case.t_min) < float(case.t_max)):
        raise ValueError(f"{source}: case {case.id!r} needs t_min < t_max, got {case.t_min} and {case.t_max}")
    if not (hasattr(case.scene, "value") and hasattr(case.scene, "info")):
        raise TypeError(f"{source}: case {case.id!r} scene must be a reference Field (e.g. CallableField), "
                        f"got {type(case.scene).__name__}")
    if not case.scene.info.exact_hits and not (np.isfinite(float(case.t_min)) and np.isfinite(float(case.t_max))):
        # (checked here rather than left to the truth: a run would skip every row of the case)
        raise ValueError(f"{source}: case {case.id!r} has no closed-form hits (its scene's exact_hits is False), so "
                         "its truth is the numerical reference, which samples the whole of [t_min, t_max]: give both "
                         f"finite (t_max: the depth past which a ray counts as a miss), got t_min={case.t_min}, "
                         f"t_max={case.t_max}")
    tags = tuple(dict.fromkeys(tuple(case.tags) + _cases._scene_tags(case.scene) + ("user",)))
    return dataclasses.replace(case, origins=np.ascontiguousarray(o), directions=np.ascontiguousarray(d), tags=tags)


def _resolve(spec: str):
    module, sep, attr = spec.partition(":")
    if not sep or not module or not attr:
        raise ValueError(f"--cases: {spec!r} is not of the form 'package.module:attribute'")
    try:
        obj = importlib.import_module(module)
    except Exception as exc:
        raise ValueError(f"--cases: cannot import {module!r} ({type(exc).__name__}: {exc}); is it on the "
                         "PYTHONPATH or installed?") from None
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise ValueError(f"--cases: {module!r} has no attribute {attr!r}")
        obj = getattr(obj, part)
    if callable(obj) and not isinstance(obj, Case):
        try:
            obj = obj()
        except Exception as exc:
            raise ValueError(f"--cases: calling {spec} failed: {type(exc).__name__}: {exc}") from None
    return obj


def load(spec: str) -> list[str]:
    """Import the cases of ``spec`` (``module:attr``), validate and register them; their ids."""
    obj = _resolve(spec)
    items = [obj] if isinstance(obj, Case) else obj
    try:
        items = list(items)
    except TypeError:
        raise TypeError(f"--cases: {spec} gave {type(obj).__name__}, expected a Case or an iterable of Cases") from None
    if not items:
        raise ValueError(f"--cases: {spec} holds no cases")
    checked = [validate(c, f"--cases {spec}") for c in items]
    ids = [c.id for c in checked]
    dup = sorted({i for i in ids if ids.count(i) > 1} | (set(ids) & set(_cases.case_ids())))
    if dup:
        raise ValueError(f"--cases: {spec} repeats or reuses case ids already in the catalog: {dup}; give them "
                         "ids of their own")
    _cases.register_cases(ids, lambda: checked)
    return ids


def load_entry_points() -> tuple[list[str], list[str]]:
    """Load every ``isobench.cases`` entry point: (ids registered, error messages).  A broken
    plug-in is reported, never fatal to the others."""
    ids, errors = [], []
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        try:
            ids += load(ep.value)
        except Exception as exc:  # one broken package must not hide the others' cases
            errors.append(f"entry point {ep.name} = {ep.value}: {exc}")
    return ids, errors
