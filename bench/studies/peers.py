"""Peers: what a user would use instead of isobench's backends, measured beside them.

Root finding (``python -m bench speed``, rows next to the backends' on the same rays):

* **numba per-ray sphere tracer** (:func:`numba_tracer`): the plain loop a user writes — per ray,
  clip to the scene's bounding sphere (the chord of the ball, hit test b² − c ≥ 0), start at
  the chord's entry (or ``t_min``), step t ← t + φ(o + t d) (L = 1: both scenes are distance
  bounds), hit when φ < ``eps`` (1e-9), miss when t passes the chord's exit or ``t_max``,
  MAX_ITER after ``max_steps`` (4096, ``hybrid_secant``'s budget).  φ is hand-written for the two scenes of :func:`bench.studies.speed.scenes`
  (unit sphere; torus R = 1, r = 0.25 ∪ box of half size 0.4) and checked against the scene tree
  before use.  Compiled with ``numba.njit`` on one thread; compile time is reported apart.
  numba is optional: without it the row is skipped with the reason.
* **scipy's Chandrupatla** (``hybrid_chandrupatla`` on the numpy backend, at its defaults):
  ``hybrid_secant``'s certified march handing its brackets to ``scipy.optimize.elementwise.find_root``
  (:mod:`impls.core.chandrupatla`) instead of refining them by secant steps.

Volume rendering (``python -m bench speed --volume``, :func:`volume_rows`): each backend's
``volume_nerf_uniform`` against the plain alpha compositing of the same samples compiled whole by
``torch.compile`` and by ``jax.jit`` (:func:`plain_compositing`): N uniform bins of [t_min, t_max],
midpoint samples t_i, σ_i = s·sigmoid(−s φ(x_i)), α_i = 1 − exp(−σ_i δ), T_i = Π_{j<i}(1 − α_j),
C = Σ T_i α_i ρ(x_i) with ρ the :class:`reference.rendering.SineColor`; one fused expression over
(rays, N), no early termination (the backends' renderers run with ``t_threshold`` = 0, the same
sum).  Compile time (first call) is reported apart from the medians of the timed calls.
"""

from __future__ import annotations

import math
import time
from typing import Any, Callable

import numpy as np

from ..run.timing import times_against_unit

#: status codes of the per-ray tracer (isobench's, :class:`impls.protocol.Status`)
_CONV, _MISS, _MAXI = 0, 2, -2


def numba_or_reason() -> tuple[Any, str | None]:
    """(the numba module, None), or (None, why the numba peer is skipped)."""
    try:
        import numba
    except ImportError as exc:
        return None, f"numba is not installed ({exc}); pip install numba to time the per-ray compiled tracer"
    return numba, None


# -- φ of the speed scenes, as scalar functions for numba --------------------------------------------


def _phi_sphere(x, y, z):
    return math.sqrt(x * x + y * y + z * z) - 1.0


def _phi_torus_box(x, y, z):
    rho = math.sqrt(x * x + y * y)
    a = rho - 1.0
    torus = math.sqrt(a * a + z * z) - 0.25
    qx, qy, qz = abs(x) - 0.4, abs(y) - 0.4, abs(z) - 0.4
    mx, my, mz = max(qx, 0.0), max(qy, 0.0), max(qz, 0.0)
    box = math.sqrt(mx * mx + my * my + mz * mz) + min(max(qx, max(qy, qz)), 0.0)
    return min(torus, box)


#: scene name of :func:`bench.studies.speed.scenes` → scalar φ(x, y, z) written for the compiled peers
SCALAR_PHI: dict[str, Callable[[float, float, float], float]] = {"sphere": _phi_sphere, "torus∪box": _phi_torus_box}


def check_scalar_phi(name: str, scene, n: int = 2000, seed: int = 0) -> None:
    """The hand-written φ of scene ``name`` equals the scene tree's φ at ``n`` random points of
    [−2, 2]³ to 1e-12 (a ValueError otherwise: the peer would trace another surface)."""
    x = np.random.default_rng(seed).uniform(-2.0, 2.0, (n, 3))
    want = np.asarray(scene.value(x, np), np.float64)
    got = np.array([SCALAR_PHI[name](*p) for p in x])
    err = float(np.max(np.abs(got - want)))
    if not err <= 1e-12:
        raise ValueError(f"peer φ for {name!r} differs from the scene's by {err:.3g}; bench/studies/peers.py is out of date")


def numba_tracer(numba, phi: Callable[[float, float, float], float]):
    """A compiled per-ray sphere tracer for the scalar φ (see the module docstring).

    ``trace(o, d, center, radius, t_min, t_max, eps, max_steps, t, status, evals)`` fills the
    last three arrays (n,): depth (inf for a miss, the last iterate for MAX_ITER), status, and the
    φ evaluations made (0 for a ray that misses the ball)."""
    phi_c = numba.njit(cache=False)(phi)

    @numba.njit(cache=False)
    def trace(o, d, center, radius, t_min, t_max, eps, max_steps, t_out, status_out, evals_out):
        for i in range(o.shape[0]):
            ox, oy, oz = o[i, 0], o[i, 1], o[i, 2]
            dx, dy, dz = d[i, 0], d[i, 1], d[i, 2]
            px, py, pz = ox - center[0], oy - center[1], oz - center[2]
            b = px * dx + py * dy + pz * dz
            disc = b * b - (px * px + py * py + pz * pz - radius * radius)
            t_out[i], status_out[i], evals_out[i] = math.inf, _MISS, 0
            if disc < 0.0:
                continue
            s = math.sqrt(disc)
            t, t1 = max(-b - s, t_min), min(-b + s, t_max)
            k = 0
            while t <= t1:
                if k >= max_steps:
                    t_out[i], status_out[i] = t, _MAXI
                    break
                f = phi_c(ox + t * dx, oy + t * dy, oz + t * dz)
                k += 1
                if f < eps:
                    t_out[i], status_out[i] = t, _CONV
                    break
                t += f
            evals_out[i] = k

    return trace


def root_peer_runs(cases: dict, repeats: int, t_max: float, unit_timer, eps: float = 1e-9,
                   max_steps: int = 4096, scipy_method: str = "hybrid_chandrupatla") -> tuple[list, list[str]]:
    """Time the peers on ``cases`` (:func:`bench.studies.speed.scenes`); returns (runs, skipped lines).

    ``runs``: ``(scene, label, RayResult, row)`` as :func:`bench.studies.speed.measure` collects its
    backends' (scored there against the exact hits).  Each timed call is preceded by the
    time unit (``unit_timer(o, d)``), as the backends' are."""
    from impls import RayResult, registry

    runs, skipped = [], []
    numba, why = numba_or_reason()
    if numba is None:
        skipped.append(f"peer numba per-ray sphere tracer: skipped: {why}")
    else:
        for name, (scene, o, d) in cases.items():
            if name not in SCALAR_PHI:
                skipped.append(f"peer numba per-ray sphere tracer on {name}: skipped: no hand-written φ for it")
                continue
            check_scalar_phi(name, scene)
            ball = scene.bounding_sphere()
            center, radius = np.asarray(ball[0], np.float64), float(ball[1])
            t0 = time.perf_counter()
            trace = numba_tracer(numba, SCALAR_PHI[name])
            n = o.shape[0]
            bufs = (np.empty(n), np.empty(n, np.int32), np.empty(n, np.int32))
            oc, dc = np.ascontiguousarray(o, np.float64), np.ascontiguousarray(d, np.float64)
            trace(oc[:1], dc[:1], center, radius, 0.0, t_max, eps, max_steps, *(b[:1] for b in bufs))  # compiles
            compile_s = time.perf_counter() - t0

            def call():
                trace(oc, dc, center, radius, 0.0, t_max, eps, max_steps, *bufs)

            t0 = time.perf_counter()
            call()
            first = time.perf_counter() - t0
            times, units, ratios, _ = times_against_unit(call, unit_timer(o, d), repeats)
            res = RayResult(t=bufs[0].copy(), status=bufs[1].copy(), iterations=bufs[2].copy(), evals=bufs[2].copy())
            runs.append((name, "peer:numba-st", res, _row(name, "peer:numba-st", f"per-ray sphere trace φ<{eps:g}",
                                                          n, times, units, ratios, compile_s, first)))
    b = registry.resolve("numpy")
    for name, (scene, o, d) in cases.items():
        p = b.prepare(scipy_method, scene, o, d, t_min=0.0, t_max=t_max)
        t0 = time.perf_counter()
        out = p.run()
        first = time.perf_counter() - t0
        times, units, ratios, out = times_against_unit(p.run, unit_timer(o, d), repeats)
        runs.append((name, "peer:scipy", p.result(out), _row(name, "peer:scipy", scipy_method, o.shape[0], times,
                                                             units, ratios, None, first)))
    return runs, skipped


def _row(scene: str, label: str, method: str, n: int, times, units, ratios, compile_s, first) -> dict:
    return {"scene": scene, "backend": label, "method": method, "rays": int(n), "time_s": float(np.median(times)),
            "unit_s": float(np.median(units)), "x_unit": float(np.median(ratios)), "x_unit_min": float(np.min(ratios)),
            "x_unit_max": float(np.max(ratios)), "target": None, "compile_s": compile_s, "first_call_s": first}


# -- volume rendering side by side ---------------------------------------------------------------------


def _sine(x, sin, matmul, asarray):
    """ρ(x) of :class:`reference.rendering.SineColor` () in the library of ``sin``."""
    from reference.rendering import SineColor

    c = SineColor()
    A = asarray(np.asarray(c.directions, np.float64).T)
    p = asarray(np.asarray(c.phases, np.float64))
    return 0.5 + 0.5 * sin(c.frequency * matmul(x, A) + p)


def plain_compositing(lib: str, scene_name: str, n_samples: int, t_min: float, t_max: float, s: float):
    """``render(o, d) -> colour (n, 3)``: the plain NeRF-density compositing of the module
    docstring for scene ``scene_name`` written in ``lib`` ("torch" or "jax") with its own ops, not
    compiled (the caller compiles it)."""
    if lib == "torch":
        import torch as M

        sigmoid, cumprod, sin = M.sigmoid, (lambda a: M.cumprod(a, dim=-1)), M.sin
        asarray = lambda a: M.as_tensor(a, dtype=M.float64)  # noqa: E731
        maximum = M.maximum
        concat_one = lambda a: M.cat([M.ones_like(a[:, :1]), a[:, :-1]], dim=-1)  # noqa: E731
        vmin = M.minimum
        vsum = lambda a, axis: M.sum(a, dim=axis)  # noqa: E731
    elif lib == "jax":
        import jax
        import jax.numpy as M

        sigmoid, cumprod, sin = jax.nn.sigmoid, (lambda a: M.cumprod(a, axis=-1)), M.sin
        asarray = lambda a: M.asarray(a, dtype=M.float64)  # noqa: E731
        maximum = M.maximum
        concat_one = lambda a: M.concatenate([M.ones_like(a[:, :1]), a[:, :-1]], axis=-1)  # noqa: E731
        vmin = M.minimum
        vsum = lambda a, axis: M.sum(a, axis=axis)  # noqa: E731
    else:
        raise ValueError(f"lib must be 'torch' or 'jax', got {lib!r}")
    delta = (t_max - t_min) / n_samples
    mids = t_min + (np.arange(n_samples) + 0.5) * delta

    def phi(x):
        X, Y, Z = x[..., 0], x[..., 1], x[..., 2]
        if scene_name == "sphere":
            return M.sqrt(X * X + Y * Y + Z * Z) - 1.0
        a = M.sqrt(X * X + Y * Y) - 1.0
        torus = M.sqrt(a * a + Z * Z) - 0.25
        q = M.abs(x) - 0.4
        mq = maximum(q, M.zeros_like(q))
        box = M.sqrt(vsum(mq * mq, -1)) + vmin(maximum(q[..., 0], maximum(q[..., 1], q[..., 2])), M.zeros_like(X))
        return vmin(torus, box)

    def render(o, d):
        t = asarray(mids)
        x = o[:, None, :] + t[None, :, None] * d[:, None, :]
        sigma = s * sigmoid(-s * phi(x))
        alpha = 1.0 - M.exp(-sigma * delta)
        T = concat_one(cumprod(1.0 - alpha))
        w = T * alpha
        return vsum(w[..., None] * _sine(x, sin, M.matmul, asarray), 1)

    return render


def _timed(fn, repeats: int, sync) -> tuple[float, list[float]]:
    t0 = time.perf_counter()
    sync(fn())
    first = time.perf_counter() - t0
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sync(fn())
        ts.append(time.perf_counter() - t0)
    return first, ts


def volume_rows(backend_ids, cases: dict, n_samples: int = 256, repeats: int = 5, sharpness: float = 50.0,
                t_min: float = 0.0, t_max: float = 6.0, method: str = "volume_nerf_uniform") -> tuple[list[dict], list[str]]:
    """Rows of time (median, min, max of ``repeats``) and compile time apart, for every backend's
    ``method`` and the compiled plain compositing in torch and jax, on ``cases`` (name →
    (scene, origins, directions), e.g. :func:`bench.studies.speed.scenes`) with ``n_samples`` samples each; with each row
    the largest colour difference from the numpy renderer's (the same sum: rounding only).
    Returns (rows, skipped lines)."""
    from impls import registry
    from reference.rendering import SineColor

    rows, skipped = [], []
    ref_colors: dict[str, np.ndarray] = {}
    knobs = dict(n_samples=n_samples, sharpness=sharpness, t_threshold=0.0)

    def add(name, label, kind, first, ts, compile_s, colors):
        if name not in ref_colors and label == "numpy":
            ref_colors[name] = colors
        ref = ref_colors.get(name)
        rows.append({"scene": name, "what": label, "kind": kind, "rays": int(cases[name][1].shape[0]),
                     "samples": n_samples, "time_s": float(np.median(ts)), "time_min_s": float(np.min(ts)),
                     "time_max_s": float(np.max(ts)), "repeats": len(ts), "compile_s": compile_s, "first_call_s": first,
                     "max_color_diff_vs_numpy": float(np.max(np.abs(colors - ref))) if ref is not None else float("nan")})

    ids = list(backend_ids)
    if "numpy" in ids:  # numpy first: the colour every other row is compared with
        ids.remove("numpy")
        ids.insert(0, "numpy")
    for bid in ids:
        b = registry.resolve(bid)
        if isinstance(b, registry.Unavailable):
            skipped.append(f"{bid}: skipped: {b.reason}")
            continue
        for name, (scene, o, d) in cases.items():
            # copies: a backend writing into its inputs must not change the next backend's rays
            p = b.prepare(method, scene, o.copy(), d.copy(), t_min=t_min, t_max=t_max, color=SineColor(), **knobs)

            def sync(out, b=b):
                b.synchronize(out)
                return out

            first, ts = _timed(p.run, repeats, sync)
            colors = p.result(p.run()).outputs["color"]
            add(name, bid, f"backend {method}", first, ts, p.compile_s, colors)
    for lib in ("torch", "jax"):
        try:
            compiled = _compile_plain(lib)
        except ImportError as exc:
            skipped.append(f"plain {lib} compositing: skipped: {exc}")
            continue
        for name, (scene, o, d) in cases.items():
            render, to_lib, sync, to_numpy = compiled(plain_compositing(lib, name, n_samples, t_min, t_max, sharpness))
            O, D = to_lib(o), to_lib(d)
            t0 = time.perf_counter()
            sync(render(O, D))
            compile_s = time.perf_counter() - t0  # the first call compiles (torch.compile, jax.jit)
            first, ts = _timed(lambda: render(O, D), repeats, sync)
            add(name, f"plain {lib}", "torch.compile" if lib == "torch" else "jax.jit", first, ts, compile_s,
                to_numpy(render(O, D)))
    return rows, skipped


def _compile_plain(lib: str):
    if lib == "torch":
        import torch

        def wrap(fn):
            return (torch.compile(fn, dynamic=False), lambda a: torch.as_tensor(a, dtype=torch.float64),
                    lambda out: out, lambda out: out.detach().numpy())
        return wrap
    import jax

    jax.config.update("jax_enable_x64", True)

    def wrap(fn):
        return (jax.jit(fn), lambda a: jax.numpy.asarray(a, dtype=jax.numpy.float64),
                lambda out: out.block_until_ready(), lambda out: np.asarray(out))
    return wrap


def format_volume(rows: list[dict]) -> str:
    import pandas as pd

    if not rows:
        return "(no rows)"
    cols = ["scene", "what", "kind", "time_s", "time_min_s", "time_max_s", "compile_s", "first_call_s",
            "max_color_diff_vs_numpy"]
    df = pd.DataFrame(rows)
    order = {s: i for i, s in enumerate(dict.fromkeys(df["scene"]))}
    df = df.iloc[np.argsort(df["scene"].map(order).to_numpy(), kind="stable")]  # scene by scene, in run order
    return df[cols].to_markdown(index=False, floatfmt=".3g")
