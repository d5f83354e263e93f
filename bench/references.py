"""The reference answers bench measures against, per case: exact normals, curvatures, dt/dθ,
the continuous rendering integral and the surface colour.

Each answer comes from the case (``Case.exact_*``, ``Case.color_field``: the reference
package's own, cached, with its stated error bound) when it provides it, else from the scene's
exact methods at the exact hits x* = o + t* d.  An answer the reference does not have is a
:class:`NotApplicable` with the reason, which bench records as a skipped quantity.  Costly
answers (the rendering integral, seconds to minutes per case and density model) are limited in
time and cached on disk (:class:`ReferenceOptions`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import time
from pathlib import Path

import numpy as np


class NotApplicable(Exception):
    """The reference has no answer for this quantity on this case (the message says why)."""


def exact_points(case) -> tuple[np.ndarray, np.ndarray]:
    """Exact hit points x* = o + t* d (rows for misses are NaN) and the hit mask."""
    t = np.asarray(case.exact_t, np.float64)
    hit = np.isfinite(t)
    x = case.origins + np.where(hit, t, np.nan)[:, None] * case.directions
    return x, hit


def _from_case_or_scene(case, attr: str, scene_method: str, what: str, cache: dict | None = None) -> np.ndarray:
    """``case.<attr>`` when the reference provides it, else ``scene.<scene_method>`` at the exact
    hits; :class:`NotApplicable` when neither knows the answer.  Memoised in ``cache`` (the
    runner keeps one per case), failures included."""
    if cache is None:
        return _lookup(case, attr, scene_method, what)
    key = ("exact", case.id, attr)
    if key not in cache:
        try:
            cache[key] = _lookup(case, attr, scene_method, what)
        except NotApplicable as exc:
            cache[key] = exc
    if isinstance(cache[key], NotApplicable):
        raise cache[key]
    return cache[key]


def _lookup(case, attr: str, scene_method: str, what: str):
    try:
        val = getattr(case, attr)
    except AttributeError:
        val = None
    except (NotImplementedError, ValueError) as exc:  # the reference says it has no such answer
        raise NotApplicable(f"no exact {what} for {case.id}: {exc}") from None
    if val is not None:
        return val
    fn = getattr(case.scene, scene_method, None)
    if fn is None:
        raise NotApplicable(f"no exact {what} for {case.id}: neither case.{attr} nor scene.{scene_method} exists")
    x, hit = exact_points(case)
    try:
        if scene_method == "hit_param_grad":
            out = np.full((case.n_rays, case.scene.param_vector().size), np.nan)
            if hit.any():
                out[hit] = fn(case.origins[hit], case.directions[hit], case.exact_t[hit])
            return out
        if not hit.any():
            raise NotApplicable(f"no ray of {case.id} hits the surface")
        res = fn(x[hit])
    except NotImplementedError as exc:
        raise NotApplicable(f"no exact {what} for {case.id}: {exc}") from None
    if isinstance(res, tuple):
        return tuple(_scatter(r, hit) for r in res)
    return _scatter(res, hit)


def _scatter(vals: np.ndarray, hit: np.ndarray) -> np.ndarray:
    vals = np.asarray(vals, np.float64)
    out = np.full((hit.size,) + vals.shape[1:], np.nan)
    out[hit] = vals
    return out


def exact_normals(case, cache: dict | None = None) -> np.ndarray:
    return np.asarray(_from_case_or_scene(case, "exact_normals", "normal_exact", "normals", cache), np.float64)


def exact_curvatures(case, cache: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(κ1, κ2) per ray; accepts the reference's tuple or an (n, 2) array."""
    k = _from_case_or_scene(case, "exact_curvatures", "curvatures_exact", "curvatures", cache)
    if isinstance(k, tuple):
        return np.asarray(k[0], np.float64), np.asarray(k[1], np.float64)
    k = np.asarray(k, np.float64)
    if k.ndim == 2 and k.shape[1] >= 2:
        return k[:, 0], k[:, 1]
    raise NotApplicable(f"case.exact_curvatures of {case.id} has shape {k.shape}, expected (n, 2) or (κ1, κ2)")


def exact_dt_dtheta(case, cache: dict | None = None) -> np.ndarray:
    return np.asarray(_from_case_or_scene(case, "exact_dt_dtheta", "hit_param_grad", "dt/dθ", cache), np.float64)


# -- per-ray error statistics -----------------------------------------------------------------


def _rendering_module():
    try:
        from reference import rendering
    except ImportError as exc:
        raise NotApplicable(f"reference.rendering is not available ({exc})") from None
    if getattr(rendering, "render_exact", None) is None:
        raise NotApplicable("reference.rendering.render_exact is not available")
    return rendering


def color_field(case):
    """The case's colour field ρ (``case.color_field``, else ``scene.color``)."""
    field = getattr(case, "color_field", None) or getattr(case.scene, "color", None)
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


def reference_rays(n: int, max_rays: int | None) -> np.ndarray:
    """Indices of the rays a costly reference is computed on: all, or ``max_rays`` evenly
    strided through 0 … n − 1 (first and last included), deterministic."""
    if max_rays is None or n <= max_rays:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max_rays).round().astype(np.int64))


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
        path = opts.disk / f"render_exact-{_disk_key(case, (model, s, opts.max_rays), rendering)}.npz" if opts.disk else None
        try:
            if path is not None and path.exists():
                z = np.load(path)
                cache[key] = (z["colors"], float(z["bound"]))
            else:
                t0 = time.perf_counter()
                with time_limit(opts.timeout_s):
                    colors, bound = rendering.render_exact(case.scene, color_field(case), model, s, case.origins[idx],
                                                           case.directions[idx], case.t_min, case.t_max)
                full = np.full((case.n_rays, 3), np.nan)
                full[idx] = np.asarray(colors, np.float64).reshape(len(idx), 3)
                cache[key] = (full, float(np.max(bound, initial=0.0)))
                cache[("reference_s",) + key[1:]] = time.perf_counter() - t0
                if path is not None:
                    path.parent.mkdir(parents=True, exist_ok=True)
                    tmp = path.with_suffix(".tmp.npz")
                    np.savez(tmp, colors=cache[key][0], bound=cache[key][1])
                    tmp.replace(path)
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


def surface_color(case) -> np.ndarray:
    """ρ(x*) at the exact first hit (NaN rows for misses)."""
    field = color_field(case)
    x, hit = exact_points(case)
    out = np.full((case.n_rays, 3), np.nan)
    if hit.any():
        c = np.asarray(field.value(x[hit]) if hasattr(field, "value") else field(x[hit]), np.float64)
        out[hit] = c.reshape(int(hit.sum()), -1)
    return out
