"""Renderers, written once against ``xp``: surface rendering and volume rendering by alpha
compositing (lecture eq. 9–10) with four density models and four samplers.

Compositing.  A ray's samples t_1 < … < t_N lie in bins [e_{i−1}, e_i] of width δ_i; with
opacities α_i, the weights are w_i = T_i α_i with T_i = Π_{j<i} (1 − α_j) (eq. 10) and
C = Σ_i w_i ρ(x_i) (eq. 9); ``opacity`` = Σ w_i = 1 − T_{N+1}.  Uniform bins with midpoint
samples make this the midpoint rule for C = ∫ T(t) σ(t) ρ(t) dt when α_i = 1 − exp(−σ_i δ_i).

Density models (s = ``sharpness``; sigmoid(z) = 1/(1 + e^{−z}); the formulas are those of
:mod:`reference.rendering` — imported, not copied, so backends and reference cannot drift):

* ``nerf``    σ = s·sigmoid(−sφ) (a logistic density of the field), α = 1 − exp(−σδ);
* ``volsdf``  σ = s·Ψ(−sφ), Ψ the unit Laplace CDF (VolSDF, Yariv et al. 2021, β = 1/s);
* ``unisurf`` α = sigmoid(−sφ(x_i)) (UNISURF, Oechsle et al. 2021: occupancy *is* alpha; not a
  density, so there is no δ → 0 limit);
* ``neus``    α_i = max((Φ(φ(e_{i−1})) − Φ(φ(e_i)))/Φ(φ(e_{i−1})), 0), Φ = sigmoid(s·) at the bin
  edges (NeuS, Wang et al. 2021, eq. 13): exact per bin for the opaque density
  ρ_NeuS = max(−(d/dt)Φ(φ)/Φ(φ), 0) where φ is monotone over the bin.

Samplers: ``uniform`` (N equal bins of [t_min, t_max], midpoints), ``stratified`` (one uniform
random point per bin, drawn by :func:`stratified_jitter` — a seeded numpy generator, so every
backend sees the same points; a backend that compiles kernels passes the draws in as ``jitter``
instead of compiling them in as constants),
``band`` (N equal bins of [t̂ − Δ, t̂ + Δ] ∩ [t_min, ∞) around the given hit t̂; rays with no
hit get colour 0 and status MISS), ``importance`` (NeRF hierarchical sampling: ``n_coarse``
uniform samples, their weights (+1e-5, as NeRF) as a piecewise-constant pdf, N more samples by
inverse CDF at u_k = (k + ½)/N, then all N + n_coarse composited, sorted, with bin edges
halfway between neighbours).

Rays are sampled and shaded in blocks of at most :data:`BLOCK_SAMPLES` samples (memory); a ray's
outputs do not depend on its block.

Early termination: samples are processed in blocks of ``BLOCK``; a sample contributes only
while T_i ≥ ``t_threshold``, and a ray whose T fell below it takes no further blocks.  numpy
and torch then evaluate nothing more for that ray (``samples_used`` counts the samples
evaluated, ``work_saved`` = 1 − samples_used/samples planned); jax computes every block under
masks (same colours and counts; the saving is reported, not realised).

Colour ρ: the ``color`` input (``ArrayBackend.prepare(..., color=...)``; a field with
``value(x, xp) -> (..., 3)``, default :class:`reference.rendering.SineColor`).  Outputs ``color``
(n, 3), ``opacity``, ``samples_used``,
``work_saved``; ``t`` is the expected depth Σ w_i t_i.

Flagged rays: a BAD_INPUT ray (non-finite origin or direction, zero direction) is not sampled and
every float output is NaN (``samples_used`` 0); a ray whose colour, opacity or depth comes out
non-finite (φ or ρ NaN along it) is NON_FINITE with every float output NaN; a band ray without a hit (t_hit = +inf) is MISS
with ``t`` = inf and colour and opacity 0 (the background), one whose t_hit is NaN or −inf NON_FINITE.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

import numpy as np

from reference import rendering as R

from ..methods import DENSITIES, SAMPLERS
from .param_grad import theta0
from .rootfind import BAD, CONV, MISS, NONF, _device, bad_rays

BLOCK = 16

#: samples in one block of rays: a volume renderer's intermediates are (rays × samples) arrays (a
#: neural field's hidden layers: ~1 KB per sample), so its rays are shaded in blocks of at most
#: this many samples (:meth:`impls.base.ArrayBackend.map_rays`), as the root finders' compacting
#: driver blocks its rays: the memory is a block's, not the camera's (figures: docs/methods.md)
BLOCK_SAMPLES = 1 << 20


def block_rows(samples_per_ray: int) -> int:
    """Rays per block (:data:`BLOCK_SAMPLES`): the largest power of two (so that a padded batch
    of rays, a power of two in jax, splits evenly) of at most ``BLOCK_SAMPLES / samples_per_ray``,
    and at least 1."""
    return 1 << max(0, (BLOCK_SAMPLES // max(1, samples_per_ray)).bit_length() - 1)


def shading_rows(model: str, n_samples: int) -> int:
    """Rays per block of a volume renderer with ``n_samples`` samples a ray whose bins are fixed
    up front (:func:`block_rows` of the points φ is evaluated at: NeuS's bin edges too)."""
    return block_rows(2 * n_samples + 1 if model == "neus" else n_samples)


#: the density models whose opacities are functions of φ at the samples and of the bins' widths
#: alone (NeuS reads φ at the bin edges): one program may hold the three and pick one at run time
#: (:class:`DensityChoice`)
SAMPLE_DENSITIES = ("nerf", "volsdf", "unisurf")
#: the "model" of the renderers whose density model is the knob ``density``, an index into
#: :data:`SAMPLE_DENSITIES` (:func:`make_volume_shading`, :func:`make_volume_impl`)
SWITCH = "switch"


@dataclasses.dataclass(frozen=True, eq=False)  # (index: a traced value in a kernel)
class DensityChoice:
    """The density model ``SAMPLE_DENSITIES[index]``, chosen by ``switch(index, branches,
    *operands)`` (``lax.switch`` semantics: ``backend.switch``), so that a compiled kernel takes
    the index as a runtime argument and one compilation serves the three models: their branches
    are the very code of each model, and the rest of the kernel is the same for all of them."""

    index: Any
    switch: Callable


def alpha(xp, model, phi, delta, s):
    """Opacity per bin, from the formulas of :mod:`reference.rendering` (one source for backends
    and reference).  ``phi``: (…, B) at the samples, or (…, B + 1) at the bin edges for NeuS;
    ``model``: a name of :data:`~impls.methods.DENSITIES` or a :class:`DensityChoice`."""
    if isinstance(model, DensityChoice):
        branches = [lambda phi, delta, m=m: alpha(xp, m, phi, delta, s) for m in SAMPLE_DENSITIES]
        return model.switch(model.index, branches, phi, delta)
    if model == "unisurf":
        return R.occupancy_alpha(phi, s, xp)
    if model == "neus":
        return R.neus_alpha(phi[..., :-1], phi[..., 1:], s, xp)
    return R.alpha_from_density(R.density(model, phi, s, xp), delta, xp)


# -- samplers ----------------------------------------------------------------------------------


def _grid(xp, t0, t1, n):
    """Edges (rays, n + 1) of n equal bins of [t0, t1] per ray."""
    u = xp.asarray(np.linspace(0.0, 1.0, n + 1), dtype=t0.dtype, device=_device(t0))
    return t0[:, None] + (t1 - t0)[:, None] * u[None, :]


def stratified_jitter(seed: int, n: int, n_samples: int, first: int = 0) -> np.ndarray:
    """The stratified sampler's offsets within its bins, u ∈ [0, 1), of rays ``first`` to
    ``first + n − 1``, shape (n, n_samples), float64: numpy's PCG64 seeded with ``seed``
    (``default_rng(seed)``), drawn row by row from ray 0, one 64-bit output per float, so a
    block of rays starts ``first · n_samples`` outputs on (``PCG64.advance``) and gets the rows
    the whole batch's draw gives it."""
    bits = np.random.PCG64(seed)
    if first:
        bits.advance(first * n_samples)
    return np.random.Generator(bits).random((n, n_samples))


def bins(xp, backend, sampler, o, d, t_min, t_max, t_hit, n_samples, knobs, jitter=None):
    """(edges (n, N + 1), sample points (n, N), status) for the samplers that fix bins up front;
    ``jitter``: the stratified sampler's offsets (:func:`stratified_jitter`) as an array of the
    backend (n, N), where a caller draws them itself; None: drawn here from ``knobs["seed"]``."""
    n = o.shape[0]
    status = xp.astype(xp.where(bad_rays(xp, o, d), BAD, CONV), xp.int32)
    t0 = xp.full_like(o[:, 0], t_min)
    t1 = xp.full_like(o[:, 0], t_max)
    if sampler == "band":
        ok = xp.isfinite(t_hit)
        inside = ok & (t_hit >= t0) & (t_hit <= t1)
        th = xp.where(inside, t_hit, t0)
        # the band is clipped to [t_min, t_max], the interval of the integral it stands for
        t0 = xp.maximum(th - knobs["delta"], t0)
        t1 = xp.minimum(th + knobs["delta"], t1)
        # t_hit as a root finder reports it: +inf a MISS, NaN (or −inf) NON_FINITE (a depth that is
        # no number is not a ray without a hit); a finite depth outside [t_min, t_max] is no hit of
        # this ray's interval: BAD_INPUT (its band was empty or reversed, bins of negative width)
        status = xp.where((status == CONV) & ~ok, xp.where(t_hit == math.inf, MISS, NONF), status)
        status = xp.astype(xp.where((status == CONV) & ok & ~inside, BAD, status), xp.int32)
    edges = _grid(xp, t0, t1, n_samples)
    if sampler == "stratified":
        u = jitter if jitter is not None else xp.asarray(stratified_jitter(knobs["seed"], n, n_samples),
                                                         dtype=o.dtype, device=_device(o))
    else:
        u = 0.5
    pts = edges[:, :-1] + (edges[:, 1:] - edges[:, :-1]) * u
    return edges, pts, status


def inverse_cdf(xp, edges, weights, n_fine):
    """n_fine samples of the piecewise-constant pdf ∝ weights on the bins ``edges`` at the
    deterministic quantiles u_k = (k + ½)/n_fine: each quantile's bin k (the cdf's interior
    values ≤ u_k, counted), its bin's values gathered with the standard's ``take_along_axis``
    (int64 indices: torch's take only those)."""
    w = weights + 1e-5
    pdf = w / xp.sum(w, axis=-1, keepdims=True)
    cdf = xp.cumulative_sum(pdf, axis=-1, include_initial=True)  # (n, Nc + 1)
    u = xp.asarray((np.arange(n_fine) + 0.5) / n_fine, dtype=edges.dtype, device=_device(edges))
    k = xp.sum(xp.astype(cdf[:, None, 1:-1] <= u[None, :, None], xp.int64), axis=-1)  # (n, Nf) bin index
    pick = lambda a: xp.take_along_axis(a, k, axis=1)  # noqa: E731
    lo, width, c0, p = pick(edges[:, :-1]), pick(edges[:, 1:] - edges[:, :-1]), pick(cdf[:, :-1]), pick(pdf)
    return lo + xp.clip((u[None, :] - c0) / p, 0.0, 1.0) * width


# -- compositing -------------------------------------------------------------------------------


def _block_alpha(xp, scene, model, s, o, d, p, e):
    """Opacities, sample points and φ evaluations per ray for samples ``p`` in bins ``e``."""
    x = o[:, None, :] + p[..., None] * d[:, None, :]
    if model == "neus":
        xe = o[:, None, :] + e[..., None] * d[:, None, :]
        return alpha(xp, model, scene.value(xe, xp), None, s), x, 2 * p.shape[1] + 1
    return alpha(xp, model, scene.value(x, xp), e[:, 1:] - e[:, :-1], s), x, p.shape[1]


def composite(xp, scene, color, o, d, edges, pts, *, model, s, threshold, compact, status):
    """Front-to-back compositing with early termination (see the module docstring).

    ``compact`` (numpy, torch): blocks of ``BLOCK`` samples, each evaluated only on the rays whose
    T is still ≥ threshold.  Otherwise (jax): all samples at once under masks, with the same
    per-sample contributions and the same counts (a block counts if T at its start is ≥ threshold).
    """
    n, N = pts.shape
    live = status == CONV
    if not compact:
        a, x, _ = _block_alpha(xp, scene, model, s, o, d, pts, edges)
        Ti = xp.cumulative_prod(1 - a, axis=-1, include_initial=True)
        keep = xp.astype(Ti[:, :-1] >= threshold, a.dtype) if threshold > 0 else xp.ones_like(a)
        w = Ti[:, :-1] * a * keep * xp.astype(live, a.dtype)[:, None]
        C = xp.sum(w[..., None] * color.value(x, xp), axis=1)
        depth = xp.sum(w * pts, axis=1)
        T = xp.prod(1 - a * keep * xp.astype(live, a.dtype)[:, None], axis=-1)  # a ray not live stays clear
        used = xp.zeros_like(o[:, 0], dtype=xp.int32)
        evals = xp.zeros_like(o[:, 0], dtype=xp.int32)
        for j0 in range(0, N, BLOCK):
            size = min(BLOCK, N - j0)
            on = live & (Ti[:, j0] >= threshold) if threshold > 0 else live
            on = xp.astype(on, xp.int32)
            used = used + on * size
            evals = evals + on * (2 * size + 1 if model == "neus" else size)
        return C, 1 - T, depth, used, evals
    C = xp.zeros_like(o)
    T = xp.ones_like(o[:, 0])
    depth = xp.zeros_like(o[:, 0])
    used = xp.zeros_like(o[:, 0], dtype=xp.int32)
    evals = xp.zeros_like(o[:, 0], dtype=xp.int32)
    for j0 in range(0, N, BLOCK):
        j1 = min(j0 + BLOCK, N)
        active = live & (T >= threshold) if threshold > 0 else live
        idx = xp.nonzero(active)[0]
        if idx.shape[0] == 0:
            break
        p = pts[idx, j0:j1]
        a, x, cost = _block_alpha(xp, scene, model, s, o[idx], d[idx], p, edges[idx, j0:j1 + 1])
        Ti = T[idx][:, None] * xp.cumulative_prod(1 - a, axis=-1, include_initial=True)  # (m, B + 1)
        keep = xp.astype(Ti[:, :-1] >= threshold, a.dtype) if threshold > 0 else xp.ones_like(a)
        w = Ti[:, :-1] * a * keep
        C[idx] = C[idx] + xp.sum(w[..., None] * color.value(x, xp), axis=1)
        depth[idx] = depth[idx] + xp.sum(w * p, axis=1)
        # T after the samples that contributed (a terminated sample leaves T unchanged)
        T[idx] = T[idx] * xp.prod(1 - a * keep, axis=-1)
        used[idx] = used[idx] + (j1 - j0)
        evals[idx] = evals[idx] + cost
    return C, 1 - T, depth, used, evals


#: the volume renderers' knobs that shade (the rest choose the samples)
SHADING_KNOBS = ("sharpness", "t_threshold")


def _check_far_end(t_max):
    if not math.isfinite(t_max):
        raise ValueError("volume rendering needs a finite t_max (the far end of the sampled interval)")


def _shade(xp, backend, scene, color, o, d, edges, pts, status, *, model, sharpness, t_threshold, planned,
           coarse_cost):
    """Composite the samples ``pts`` in bins ``edges`` (:func:`composite`) into the method's outputs."""
    o_safe = xp.where(xp.isfinite(o), o, xp.zeros_like(o))
    d_safe = xp.where(xp.isfinite(d), d, xp.zeros_like(d))

    def shade_block(o, d, edges, pts, status):
        return composite(xp, scene, color, o, d, edges, pts, model=model, s=sharpness, threshold=t_threshold,
                         compact=backend.compact, status=status)

    # φ (and ρ) at every sample of a block: NeuS reads the bin edges too
    per_ray = edges.shape[1] + pts.shape[1] if model == "neus" else pts.shape[1]
    C, opacity, depth, used, evals = backend.map_rays(shade_block, (o_safe, d_safe, edges, pts, status),
                                                      block_rows(per_ray))
    ok = status == CONV
    evals = evals + xp.astype(ok, xp.int32) * coarse_cost
    saved = xp.astype(planned - used, o.dtype) / planned
    # a non-finite colour, opacity or depth (φ or ρ NaN along the ray) is NON_FINITE, not a result
    finite = xp.isfinite(depth) & xp.isfinite(opacity) & xp.all(xp.isfinite(C), axis=1)
    status = xp.astype(xp.where(ok & ~finite, NONF, status), xp.int32)
    ok = status == CONV
    # flagged rays (BAD_INPUT, NON_FINITE): every float output NaN; MISS (band, no hit): t = inf,
    # colour and opacity 0 (the background), nothing sampled
    bad = (status == BAD) | (status == NONF)
    nan = xp.full_like(depth, math.nan)
    t = xp.where(ok, depth, xp.where(bad, nan, xp.full_like(depth, math.inf)))
    return {"t": t, "status": status, "iterations": used, "evals": evals,
            "color": xp.where(bad[:, None], xp.full_like(C, math.nan), C),
            "opacity": xp.where(bad, nan, opacity), "samples_used": used,
            "work_saved": xp.where(bad, nan, saved)}


def make_volume_sampler(sampler):
    """The samples of a sampler that fixes its bins up front (``uniform``, ``stratified``,
    ``band``): ``sample(backend, scene, o, d, *, t_min, t_max, t_hit, n_samples, **knobs)`` →
    ``{"edges", "pts", "status"}`` (:func:`bins`; the scene is not read).  ``sample.draws_jitter``:
    whether it takes the keyword ``jitter`` (the stratified sampler: its offsets, given by a caller
    that draws them itself; they are drawn from the knob ``seed`` otherwise)."""

    def sample(backend, scene, o, d, *, t_min, t_max, t_hit, n_samples, jitter=None, **knobs):
        _check_far_end(t_max)
        edges, pts, status = bins(backend.xp, backend, sampler, o, d, t_min, t_max, t_hit, n_samples, knobs, jitter)
        return {"edges": edges, "pts": pts, "status": status}

    sample.__name__ = f"volume_samples_{sampler}"
    sample.draws_jitter = sampler == "stratified"
    return sample


def _chosen(backend, model, knobs: dict):
    """The model a renderer of ``model`` shades with: ``model`` itself, or for :data:`SWITCH` the
    :class:`DensityChoice` of the knob ``density`` (taken out of ``knobs``)."""
    if model != SWITCH:
        return model
    if "density" not in knobs:
        raise TypeError(f"a renderer of model {SWITCH!r} needs the knob density, an index into {SAMPLE_DENSITIES}")
    return DensityChoice(knobs.pop("density"), backend.switch)


def make_volume_shading(model):
    """Density model ``model`` composited over given samples: ``shade(backend, scene, o, d, *,
    samples, color, sharpness, t_threshold)``, ``samples`` a sampler's output
    (:func:`make_volume_sampler`); the same outputs as the method of that sampler.  ``model``
    :data:`SWITCH`: the model ``SAMPLE_DENSITIES[density]``, ``density`` one more keyword."""

    def shade(backend, scene, o, d, *, samples, color, sharpness, t_threshold, **choice):
        m = _chosen(backend, model, choice)
        if choice:
            raise TypeError(f"{shade.__name__} got unexpected knobs {sorted(choice)}")
        n_samples = samples["pts"].shape[1]
        return _shade(backend.xp, backend, scene, color, o, d, samples["edges"], samples["pts"], samples["status"],
                      model=m, sharpness=sharpness, t_threshold=t_threshold, planned=n_samples, coarse_cost=0)

    shade.__name__ = f"volume_shading_{model}"
    shade.model = model
    shade.knobs = SHADING_KNOBS + (("density",) if model == SWITCH else ())  # its knobs; the sampler takes the others
    return shade


def make_volume_impl(model, sampler):
    """A ``volume_<model>_<sampler>`` implementation; ``backend.compact``: drop terminated rays
    (numpy, torch).  For the samplers that fix their bins up front it is a sampler followed by a
    shading of the model (``impl.stages`` = (sample, shade), :func:`make_volume_sampler`,
    :func:`make_volume_shading`), so a backend that compiles kernels may compile the two apart: a
    model's shading is then one kernel for the three samplers.  ``model`` :data:`SWITCH`: the
    density model ``SAMPLE_DENSITIES[density]``, ``density`` one more knob (not a method of the
    catalog: a backend that compiles kernels runs the methods of those models as one kernel,
    :meth:`impls.jax.backend.JaxBackend.compile_configuration`)."""
    if sampler != "importance":
        sample, shade = make_volume_sampler(sampler), make_volume_shading(model)

        def impl(backend, scene, o, d, *, t_min, t_max, t_hit, color, n_samples, sharpness, t_threshold, jitter=None,
                 **knobs):
            xp = backend.xp
            choice = {"density": knobs.pop("density")} if model == SWITCH and "density" in knobs else {}
            # the stratified draws of each block made in that block (PCG64 advanced to its first ray),
            # where the backend's blocks are a loop over slices; drawn whole where they are mapped
            # inside a kernel (a traced block does not know its first ray)
            per_block = sampler == "stratified" and jitter is None
            if per_block and not getattr(type(backend).map_rays, "loops_over_slices", False):
                jitter = xp.asarray(stratified_jitter(knobs["seed"], o.shape[0], n_samples), dtype=o.dtype,
                                    device=_device(o))
                per_block = False

            def block(o, d, t_hit, jitter, ray):
                if per_block:
                    first = 0 if ray is None else int(ray[0])  # (None: no ray)
                    jitter = xp.asarray(stratified_jitter(knobs["seed"], o.shape[0], n_samples, first),
                                        dtype=o.dtype, device=_device(o))
                samples = sample(backend, scene, o, d, t_min=t_min, t_max=t_max, t_hit=t_hit, n_samples=n_samples,
                                 jitter=jitter, **knobs)
                return shade(backend, scene, o, d, samples=samples, color=color, sharpness=sharpness,
                             t_threshold=t_threshold, **choice)

            # the bins by blocks too (16–24 bytes a sample: edges, points, draws), the shading's blocks
            ray = xp.arange(o.shape[0], device=_device(o)) if per_block and o.shape[0] else None
            return backend.map_rays(block, (o, d, t_hit, jitter, ray), shading_rows(model, n_samples))

        impl.stages = (sample, shade)
        impl.draws_jitter = sample.draws_jitter
        impl.__name__ = f"volume_{model}_{sampler}"
        return impl

    def impl(backend, scene, o, d, *, t_min, t_max, t_hit, color, n_samples, sharpness, t_threshold, **knobs):
        xp = backend.xp
        _check_far_end(t_max)
        nc = knobs["n_coarse"]
        m = _chosen(backend, model, knobs)

        def block(o, d):
            e0, p0, status = bins(xp, backend, "uniform", o, d, t_min, t_max, None, nc, knobs)
            o_safe = xp.where(xp.isfinite(o), o, xp.zeros_like(o))
            d_safe = xp.where(xp.isfinite(d), d, xp.zeros_like(d))
            xc = o_safe[:, None, :] + (e0 if model == "neus" else p0)[..., None] * d_safe[:, None, :]
            a = alpha(xp, m, scene.value(xc, xp), e0[:, 1:] - e0[:, :-1], sharpness)
            w = xp.cumulative_prod(1 - a, axis=-1, include_initial=True)[:, :-1] * a
            fine = inverse_cdf(xp, e0, w, n_samples)
            pts = xp.sort(xp.concat([p0, fine], axis=1), axis=1)
            mids = 0.5 * (pts[:, 1:] + pts[:, :-1])
            edges = xp.concat([e0[:, :1], mids, e0[:, -1:]], axis=1)
            return _shade(xp, backend, scene, color, o, d, edges, pts, status, model=m, sharpness=sharpness,
                          t_threshold=t_threshold, planned=nc + n_samples,
                          coarse_cost=nc + (1 if model == "neus" else 0))

        # the sampler by blocks too: inverse_cdf counts, for every quantile, the bins below it, a
        # (rays, n_samples, n_coarse) integer array in numpy and torch, an eighth of a sample's
        # cost each (φ's temporaries at a sample: ~100 bytes for a primitive, ~1 KB for a neural
        # field); a block's shading is then one block
        return backend.map_rays(block, (o, d), block_rows(n_samples * nc // 8 + 2 * (nc + n_samples) + 1))

    impl.__name__ = f"volume_{model}_{sampler}"
    return impl


def render_surface(backend, scene, o, d, *, t_min, t_max, t_hit, color, theta=None, hit=None, **knobs):
    """``render_surface``: ρ at the first hit found by the backend's hybrid root finder; 0 on a
    miss; NaN on a ray the root finder did not resolve (any other status; ``t`` NaN on BAD_INPUT).

    ``hit``: that root finder's output on these rays (``t``, ``status``, ``iterations``,
    ``evals``), where the backend ran it already: the root method :data:`render_surface.hit_method
    <render_surface>` (``hybrid_secant``) with these knobs is the same algorithm, so a backend
    that compiles kernels runs that method's kernel and shades its hit in a second one
    (:meth:`impls.jax.backend.JaxBackend.compile_configuration`); only with ``theta`` not given
    (a caller's θ moves the hit).

    Differentiable through the hit (backends with autodiff, i.e. with a ``backend.stop_gradient``):
    the colour is ρ(o + t d) with IDR's depth (Yariv et al. 2020, eq. 3; lecture eq. 7–8) t = t̂ − φ(x̂; θ)/⟨∇φ(x̂; θ₀), d⟩, where the hit t̂ (root finder) and
    ∇φ(x̂) are constants.  Its value is t̂ up to φ(x̂)/⟨∇φ, d⟩ (the root finder's residual),
    and its first derivatives in θ, o and d are those of the exact hit depth, so ∂C/∂θ =
    J_ρ(x) d (∂t/∂θ) with ∂t/∂θ = −(∂φ/∂θ)/⟨∇φ, d⟩.  Pass ``theta`` (the scene's parameter
    vector as a backend array, e.g. a torch tensor with ``requires_grad``) to differentiate in
    it; the default is the scene's own parameters.  The correction costs one ∇φ and one φ
    evaluation per hit, counted in ``evals``.  numpy (no autodiff) returns ρ at t̂ itself.
    """
    xp = backend.xp
    stop_gradient = backend.stop_gradient
    differentiable = stop_gradient is not None
    given = theta is not None  # a caller's θ: the root finder uses it (and so no ray bounds)
    if differentiable and theta is None:
        theta = theta0(backend, scene, o)
    const = stop_gradient if differentiable else (lambda a: a)
    th_c = None if theta is None else const(theta)
    if hit is not None and given:
        raise ValueError("render_surface: a precomputed hit is the hit at the scene's own parameters; with theta "
                         "given, let the root finder run")
    s = hit if hit is not None else backend.solve("render_surface", scene, const(o), const(d), t_min=t_min,
                                                  t_max=t_max, theta=th_c if given else None, **knobs)
    ok = s["status"] == CONV
    o_safe = xp.where(xp.isfinite(o), o, xp.zeros_like(o))
    d_safe = xp.where(xp.isfinite(d), d, xp.zeros_like(d))
    t = xp.where(ok, s["t"], xp.zeros_like(s["t"]))
    evals = s["evals"]
    if differentiable:
        t_hat = stop_gradient(t)
        x_hat = stop_gradient(o_safe) + t_hat[:, None] * stop_gradient(d_safe)
        g, _, c1 = backend.grad_hess(scene, x_hat, False, th_c)
        gd = stop_gradient(xp.sum(g * d_safe, axis=-1))
        gd = xp.where(ok & (gd != 0), gd, xp.ones_like(gd))
        x0 = o_safe + t_hat[:, None] * d_safe  # carries ∂/∂o, ∂/∂d of φ(o + t̂ d)
        t = t_hat - xp.where(ok, scene.value(x0, xp, theta) / gd, xp.zeros_like(gd))
        evals = evals + xp.astype(ok, evals.dtype) * (c1 + 1)
    x = o_safe + t[:, None] * d_safe
    rgb = color.value(x, xp)
    # CONVERGED: ρ at the hit; MISS: 0 (the background); any other status (BAD_INPUT,
    # MAX_ITER, NON_FINITE, LIPSCHITZ_VIOLATED, UNCERTIFIED): NaN, the status says why
    status = xp.astype(xp.where(ok & ~xp.all(xp.isfinite(rgb), axis=1), NONF, s["status"]), xp.int32)
    ok = status == CONV
    miss = status == MISS
    blank = xp.where(miss, xp.zeros_like(s["t"]), xp.full_like(s["t"], math.nan))
    bad = status == BAD
    return {"t": xp.where(bad, xp.full_like(s["t"], math.nan), s["t"]), "status": status,
            "iterations": s["iterations"], "evals": evals,
            "color": xp.where(ok[:, None], rgb, xp.broadcast_to(blank[:, None], rgb.shape))}


#: the root method whose algorithm render_surface's hit is (the same knobs, the same catalog builder)
render_surface.hit_method = "hybrid_secant"

IMPLS = {"render_surface": render_surface,
         **{f"volume_{model}_{sampler}": make_volume_impl(model, sampler) for model in DENSITIES for sampler in SAMPLERS}}
#: the renderers of the model :data:`SWITCH`, by sampler (not methods of the catalog)
SWITCHED = {sampler: make_volume_impl(SWITCH, sampler) for sampler in SAMPLERS}
#: the catalog's renderers of the models of :data:`SAMPLE_DENSITIES`: method → (the model's index
#: there, the knob ``density`` of the model :data:`SWITCH`; the sampler)
DENSITY_CHOICES = {f"volume_{m}_{s}": (i, s) for i, m in enumerate(SAMPLE_DENSITIES) for s in SAMPLERS}
#: the shading of the model :data:`SWITCH` (one object: a backend's kernels find it by name)
SWITCH_SHADING = make_volume_shading(SWITCH)
