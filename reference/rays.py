"""Ray families: seeded generators of (origins, unit directions), float64, shape (n, 3)."""

from __future__ import annotations

import numpy as np

from .arrays import unit


#: rows divided by their norm; one helper for the whole reference (``scene.unit``)
normalize = unit


def unit_tolerance(*dtypes) -> float:
    """|‖d‖ − 1| allowed for a direction: 8·√3·ε of the coarsest of ``dtypes`` (a direction
    normalised in that precision is within a few ε of unit length: 3 rounded squares, a rounded
    sum and square root, 3 rounded quotients).  float64: 3.1e-15; float32: 1.7e-6.  The one
    tolerance of the backends (:func:`impls.base.check_rays`), the numerical reference and a
    user's cases (:func:`reference.user_cases.validate`)."""
    eps = max(float(np.finfo(dt).eps) if np.dtype(dt).kind == "f" else float(np.finfo(np.float64).eps)
              for dt in dtypes)
    return 8.0 * float(np.sqrt(3.0)) * eps


def unit_directions(d: np.ndarray, tol: float, name: str, dtypes: str) -> np.ndarray:
    """``d`` (float64, ``(n, 3)``) held to unit length within ``tol`` on its finite, non-zero rows
    (a ValueError naming ``name``, ``dtypes`` (the dtypes ``tol`` is for), the worst ray and the
    fix), and the rows unit only to more than float64's rounding (accepted under a coarser dtype's
    ``tol``: normalised in float32) normalised again in float64, in a copy.  The methods and the
    numerical reference measure distance in t (steps φ/L, chords), so that ray is the one solved:
    with ‖d‖ = 1 + 1e-7 a step from 1,000 away moved 1e-4 further than φ/L, across a 1e-5 shell.
    The one check of :func:`impls.base.check_rays` and :mod:`reference.numerical`."""
    finite = np.all(np.isfinite(d), axis=1)
    with np.errstate(over="ignore"):
        dn = np.linalg.norm(np.where(finite[:, None], d, 0.0), axis=1)
    dev = np.where(finite & (dn > 0), np.abs(dn - 1.0), 0.0)
    if np.any(dev > tol):
        i = int(np.argmax(dev))
        raise ValueError(
            f"{name} must be unit vectors (|‖d‖ − 1| ≤ {tol:.1e} for {dtypes}); {int(np.count_nonzero(dev > tol))} of "
            f"{len(d)} are not, the worst (ray {i}) has ‖d‖ − 1 = {dn[i] - 1:.3e}. Normalise them in float64: "
            f"{name} = np.asarray({name}, np.float64); {name} = {name} / np.linalg.norm({name}, axis=1, keepdims=True)")
    coarse = dev > unit_tolerance(np.float64)
    if np.any(coarse):
        d = d.copy()
        d[coarse] /= dn[coarse, None]
    return d


def pinhole(eye, look_at, up=(0.0, 1.0, 0.0), fov_deg: float = 40.0, width: int = 64, height: int = 64):
    """Pinhole camera rays through pixel centres, row-major from the top-left pixel.

    The image plane at distance 1 spans tan(fov/2) vertically (fov is the vertical field of
    view, degrees) and keeps square pixels.  Returns ``origins`` (all equal to ``eye``) and
    unit ``directions``.  A ValueError names the argument when the camera is undefined: ``look_at``
    equal to ``eye``, ``up`` zero or parallel to the view direction, a non-finite vector, a field
    of view outside (0°, 180°), or a non-positive image size.
    """
    vecs = {}
    for name, v in (("eye", eye), ("look_at", look_at), ("up", up)):
        a = np.asarray(v, np.float64)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise ValueError(f"pinhole: {name} must be 3 finite numbers, got {v!r}")
        vecs[name] = a
    eye, view = vecs["eye"], vecs["look_at"] - vecs["eye"]
    scale = max(np.abs(vecs["look_at"]).max(), np.abs(eye).max(), 1.0)
    if not np.linalg.norm(view) > 8 * np.finfo(np.float64).eps * scale:
        raise ValueError(f"pinhole: look_at={look_at!r} equals eye={tuple(eye.tolist())}: the view direction "
                         "look_at − eye is undefined; put look_at where the camera looks, away from eye")
    forward = normalize(view)
    up_v = vecs["up"]
    side = np.cross(forward, up_v)
    # |forward × up| = |up| sin(angle): below ~1e-8·|up| the image's horizontal axis is rounding noise
    if not np.linalg.norm(side) > 1e-8 * np.linalg.norm(up_v):
        raise ValueError(f"pinhole: up={up!r} is parallel to the view direction look_at − eye "
                         f"({tuple(np.round(forward, 6).tolist())}) or zero: the image's horizontal axis is undefined; "
                         "pass an up vector not parallel to it (e.g. (0, 0, 1) when looking along ±y)")
    for name, v in (("fov_deg", fov_deg),):
        if not (isinstance(v, (int, float)) and 0 < float(v) < 180):
            raise ValueError(f"pinhole: {name} must be in (0, 180) degrees, got {v!r}")
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise ValueError(f"pinhole: {name} must be a whole number ≥ 1 (pixels), got {v!r}")
    right = normalize(side)
    true_up = np.cross(right, forward)
    half_h = np.tan(np.radians(fov_deg) / 2)
    half_w = half_h * width / height
    u = (np.arange(width) + 0.5) / width * 2 - 1
    v = 1 - (np.arange(height) + 0.5) / height * 2
    uu, vv = np.meshgrid(u * half_w, v * half_h)
    dirs = forward + uu[..., None] * right + vv[..., None] * true_up
    dirs = normalize(dirs.reshape(-1, 3))
    origins = np.broadcast_to(eye, dirs.shape).copy()
    return origins, dirs


def _perp_frames(w: np.ndarray, rng) -> np.ndarray:
    """A random unit vector orthogonal to each unit row of ``w``."""
    p = rng.normal(size=w.shape)
    p -= np.einsum("ij,ij->i", p, w)[:, None] * w
    return normalize(p)


def random_directions(n: int, seed: int) -> np.ndarray:
    """n unit vectors uniform on the sphere (normalised Gaussians)."""
    return normalize(np.random.default_rng(seed).normal(size=(n, 3)))


def impact(n: int, impact_parameter, distance: float, seed: int, center=(0.0, 0.0, 0.0)):
    """Rays from ``distance`` away aimed to pass ``impact_parameter`` (scalar or (n,)) from
    ``center``: o = c + distance·w + b·p, d = −w, w random unit, p ⟂ w random unit.  For a
    sphere of radius 1 at c, b = 1 ± 10⁻ᵏ gives grazing hits and near misses."""
    rng = np.random.default_rng(seed)
    w = normalize(rng.normal(size=(n, 3)))
    p = _perp_frames(w, rng)
    b = np.broadcast_to(np.asarray(impact_parameter, np.float64), (n,))
    o = np.asarray(center, np.float64) + distance * w + b[:, None] * p
    return o, -w


def grazing_pm(n: int, k: float, distance: float, seed: int, radius: float = 1.0, center=(0.0, 0.0, 0.0)):
    """Half the rays at impact parameter r(1 + 10⁻ᵏ) (near misses), half at r(1 − 10⁻ᵏ)
    (grazing hits), alternating."""
    b = radius * (1.0 + np.where(np.arange(n) % 2 == 0, 1.0, -1.0) * 10.0 ** (-k))
    return impact(n, b, distance, seed, center)


def in_ball(n: int, radius: float, seed: int, center=(0.0, 0.0, 0.0)):
    """Origins uniform in the ball of ``radius`` about ``center``, directions uniform."""
    rng = np.random.default_rng(seed)
    u = normalize(rng.normal(size=(n, 3)))
    o = np.asarray(center, np.float64) + radius * rng.uniform(size=(n, 1)) ** (1 / 3) * u
    return o, normalize(rng.normal(size=(n, 3)))


def far(n: int, distance: float, target_radius: float, seed: int):
    """Origins at ``distance`` from the origin in random directions, aimed at random points in
    the ball of ``target_radius`` (so most rays hit an object of that size)."""
    rng = np.random.default_rng(seed)
    o = distance * normalize(rng.normal(size=(n, 3)))
    target = target_radius * rng.uniform(-1, 1, size=(n, 3)) / np.sqrt(3)
    return o, normalize(target - o)
