"""What bench adds to the case's own exact answers: the rendering integral under bench's limits.

The exact answers themselves (hit depth and points, normals, curvatures, dt/dθ, the surface
colour ρ(x*)) come from the case, the one source of them (``Case.exact_*`` in
:mod:`reference.cases`, cached on the case; a missing one is a
:class:`reference.cases.NoExactAnswer`).  What is bench-specific lives here: the continuous
rendering integral C = ∫ T σ ρ dt for a method's density model, a costly reference (seconds to
minutes per case and density) computed on a strided subset of the rays
(:func:`reference_rays`), limited in time and cached on disk (:class:`ReferenceOptions`); the
density model a method's name or knobs select (:func:`density_model`); and
:class:`NotApplicable`, how bench says a quantity it could not check is skipped, and why.
"""

from __future__ import annotations

import dataclasses
import hashlib
import time
from pathlib import Path

import numpy as np

from impls.cache import source_digest

from .results import write_atomic

class NotApplicable(Exception):
    """bench cannot check this quantity on this case (the message says why): no colour field,
    a suite that skips costly references, a rendering integral past its time limit.  (The case's
    own missing answers are :class:`reference.cases.NoExactAnswer`; bench records both as a
    skipped quantity.)"""


def _rendering_module():
    try:
        from reference import rendering
    except ImportError as exc:
        raise NotApplicable(f"reference.rendering is not available ({exc})") from None
    if getattr(rendering, "render_exact", None) is None:
        raise NotApplicable("reference.rendering.render_exact is not available")
    return rendering


def color_field(case):
    """The case's colour field ρ (``case.color_field``)."""
    field = getattr(case, "color_field", None)
    if field is None:
        raise NotApplicable(f"{case.id} has no colour field ρ (case.color_field)")
    return field


def density_model(spec, knobs: dict) -> str | None:
    """The density model a volume renderer uses: a ``density``/``model`` knob, else the model
    named in the method name (``volume_<model>_<sampler>``); None for a surface renderer."""
    for k in ("density", "model"):
        if isinstance(knobs.get(k), str):
            return knobs[k]
    try:
        models = _rendering_module().MODELS
    except (NotApplicable, AttributeError):
        models = ("nerf", "unisurf", "neus", "volsdf")
    parts = spec.name.split("_")
    return next((m for m in models if m in parts), None)


@dataclasses.dataclass(frozen=True)
class ReferenceOptions:
    """How costly reference answers are obtained (the runner stores one in the per-run cache
    under ``"_options"``).  ``expensive``: compute references that take seconds to minutes per
    case (the rendering integral); ``timeout_s``: limit per such computation (0: none);
    ``disk``: directory caching them across runs (keyed by the case version and the source of the
    reference module, so a changed case or reference is recomputed); ``max_rays``: the rendering
    integral is computed on at most this many rays of a case, evenly strided through the ray
    list (:func:`reference_rays`; None: all) — it costs ~0.1 s per ray on smooth scenes and ~1 s
    where φ has kinks, so a 4096-ray case would take minutes per density."""

    expensive: bool = True
    timeout_s: float = 30.0
    disk: Path | None = None
    max_rays: int | None = 32


def _disk_key(case, parts: tuple, module) -> str:
    h = hashlib.sha256(repr((case.version, parts)).encode())
    try:
        h.update(Path(module.__file__).read_bytes())
    except (OSError, TypeError, AttributeError):
        pass
    return h.hexdigest()[:20]


def load_numerical_hits(case, disk: Path | None) -> None:
    """Give ``case`` its numerical first hits (``Case.exact_t`` and its error bounds, for a scene
    without closed-form hits: an MLP, the neural SDF; 1.5 s and 0.75 s on the quick run's two
    cameras) from ``disk``, or compute and store them there.  Keyed by the case's version (scene
    spec, rays, depth range) and the source of the whole ``reference`` package, so changed code
    recomputes them.  Nothing for a case with closed-form hits or without ``disk``; a missing
    answer (``NoExactAnswer``) or a file that cannot be read is computed as before, not stored."""
    if disk is None or case.scene.info.exact_hits:
        return
    h = hashlib.sha256(repr(("first_hit_numeric", case.version)).encode())
    h.update(source_digest("reference").encode())
    path = Path(disk) / f"first_hit-{case.id}-{h.hexdigest()[:20]}.npz"

    try:
        case.preload_answer("t", lambda: _kept_arrays(path, ("t", "bounds"), case.numerical_hits))
    except Exception:  # noqa: BLE001 - the case's own error: raised again where the answer is read
        pass


def render_exact_kept(disk: Path | None, scene, color, model: str, sharpness: float, o, d, t_min: float,
                      t_max: float):
    """``reference.rendering.render_exact(scene, color, model, sharpness, o, d, t_min, t_max)``,
    kept in ``disk`` (None: computed every time) by all of its inputs (the scene's spec, the colour
    field's repr, the rays' float64 bytes) and the source of the ``reference`` package.  For the
    claims' integrals (seconds per ray on a sharp density), which the run's
    :func:`exact_color` does not cover."""
    rendering = _rendering_module()
    o, d = np.ascontiguousarray(o, np.float64), np.ascontiguousarray(d, np.float64)
    if disk is None:
        return rendering.render_exact(scene, color, model, sharpness, o, d, t_min, t_max)
    h = hashlib.sha256(repr(("render_exact", scene.spec(), repr(color), model, float(sharpness), float(t_min),
                             float(t_max), o.shape)).encode())
    h.update(o.tobytes() + d.tobytes() + source_digest("reference").encode())
    path = Path(disk) / f"render_exact-kept-{h.hexdigest()[:24]}.npz"
    return _kept_arrays(path, ("colors", "bounds"),
                        lambda: rendering.render_exact(scene, color, model, sharpness, o, d, t_min, t_max))


def _kept_arrays(path: Path, names: tuple[str, ...], compute) -> tuple:
    """The float64 arrays ``names`` stored in the ``.npz`` file ``path``, or ``compute()``'s (a
    tuple in that order), then written there atomically; a file that cannot be read is computed
    again and replaced."""
    try:
        with np.load(path) as z:
            return tuple(z[n] for n in names)
    except (OSError, KeyError, ValueError):
        pass
    values = tuple(np.asarray(v, np.float64) for v in compute())

    def save(tmp):
        with open(tmp, "wb") as f:  # a file, not a name: savez would append ".npz"
            np.savez(f, **dict(zip(names, values)))

    write_atomic(path, save)
    return values


def reference_rays(n: int, max_rays: int | None) -> np.ndarray:
    """Indices of the rays a costly reference is computed on: all, or ``max_rays`` evenly
    strided through 0 … n − 1 (first and last included), deterministic."""
    if max_rays is None or n <= max_rays:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max_rays).round().astype(np.int64))


def integral_key(case, spec, knobs: dict, opts: ReferenceOptions) -> tuple | None:
    """The cache key of the rendering integral :func:`exact_color` computes for a method with
    ``knobs`` on ``case`` — ``("render_exact", case id, density model, sharpness)`` — or None when
    it computes none (a surface renderer, no sharpness knob, no colour field, a suite without
    costly references).  What :mod:`bench.run.cluster` plans its shared reference tasks by."""
    if getattr(spec, "family", None) != "render" or not opts.expensive or "sharpness" not in knobs:
        return None
    if getattr(case, "color_field", None) is None:
        return None
    model = density_model(spec, knobs)
    return None if model is None else ("render_exact", case.id, model, float(knobs["sharpness"]))


def exact_color(case, spec, knobs: dict, cache: dict) -> tuple[np.ndarray, float]:
    """C = ∫ T σ ρ dt by ``reference.rendering.render_exact`` for the method's density model and
    sharpness over [t_min, t_max] of the case; (colours (n, 3), its largest error bound).  Cached
    per case × model × sharpness (sample counts and samplers do not change the integral), in
    memory and, with :attr:`ReferenceOptions.disk`, on disk; a computation past
    :attr:`ReferenceOptions.timeout_s` is a :class:`NotApplicable` (remembered for the run, per
    case and model).  Only the rays of :func:`reference_rays` get a colour; the others are NaN
    rows, which the metrics leave out."""
    from .timing import Timeout, time_limit

    opts: ReferenceOptions = cache.get("_options") or ReferenceOptions()
    model = density_model(spec, knobs)
    if model is None:
        raise NotApplicable(f"{spec.name} renders the surface; its reference is ρ(x*) (color_vs_surface)")
    if "sharpness" not in knobs:
        raise NotApplicable(f"{spec.name} has no 'sharpness' knob: the density of its integral is unknown")
    if not opts.expensive:
        raise NotApplicable("this suite skips the rendering integral (a costly reference, seconds to minutes per "
                            "case and density); --suite full computes it")
    s = float(knobs["sharpness"])
    key = ("render_exact", case.id, model, s)
    gave_up = cache.get(("render_exact_timed_out", case.id, model))
    if key not in cache and gave_up:  # one timeout per model and run: not retried on every case
        cache[key] = NotApplicable(gave_up)
    if key not in cache:
        rendering = _rendering_module()
        idx = reference_rays(case.n_rays, opts.max_rays)
        # (the colour field is not part of the case's version: its repr, with its frequency, keys the file)
        parts = (model, s, opts.max_rays, repr(color_field(case)))
        path = opts.disk / f"render_exact-{_disk_key(case, parts, rendering)}.npz" if opts.disk else None
        def compute():
            t0 = time.perf_counter()
            with time_limit(opts.timeout_s):
                colors, bound = rendering.render_exact(case.scene, color_field(case), model, s, case.origins[idx],
                                                       case.directions[idx], case.t_min, case.t_max)
            full = np.full((case.n_rays, 3), np.nan)
            full[idx] = np.asarray(colors, np.float64).reshape(len(idx), 3)
            cache[("reference_s",) + key[1:]] = time.perf_counter() - t0
            return full, float(np.max(bound, initial=0.0))

        try:
            colors, bound = compute() if path is None else _kept_arrays(path, ("colors", "bound"), compute)
            cache[key] = (colors, float(bound))
        except ValueError as exc:  # e.g. UNISURF: no continuous density, no integral
            cache[key] = NotApplicable(f"no continuous reference for {model}: {exc}")
        except Timeout:
            cache[key] = NotApplicable(f"the reference integral for {model} (s = {s:g}) took longer than "
                                       f"{opts.timeout_s:g} s (--reference-timeout); not checked")
            cache[("render_exact_timed_out", case.id, model)] = (
                f"the reference integral for {model} timed out on {case.id} (> {opts.timeout_s:g} s); not attempted "
                f"again in this run")
    if isinstance(cache[key], NotApplicable):
        raise cache[key]
    return cache[key]
