"""Claim 6: bisection, Newton and secant along a ray — observed convergence orders near a simple root, and
the secant's dependence on its initial guesses (lecture, "Ray marching in implicit surfaces").

The iterations are the object of study, so they are written here, in mpmath at 300 digits: orders are
then visible over many steps instead of the 2–4 steps float64 allows .  g(t) = φ(o + t d) for a sphere SDF, the algebraic sphere and a torus SDF along an oblique ray;
the root is polished by mpmath's Newton at 400 digits from the float64 reference, so the error of
each iterate is known to ≪ 1e-300.

Order estimate: least-squares slope q of log e_{n+1} against log e_n over the iterates with
1e-280 < e < 1e-6 (the asymptotic range); bisection: ratio exp(slope of log e_n against n) over 200
steps (its error is not monotone, its rate is).
"""

from __future__ import annotations

import mpmath as mp
import numpy as np

from .figures import figure
from .ledger import LEDGER, Evidence, Trial
from .stats import fit_power

GOLDEN = (1 + 5**0.5) / 2
O = (0.25, 0.15, 3.0)
D_RAW = (-0.05, 0.02, -1.0)
# the torus needs its own ray: the one above passes through the hole; this one crosses the tube twice
RAYS = {"torus SDF R=1 r=0.4": ((-2.5, 0.1, 0.45), (1.0, 0.0, -0.12))}


def _ray_mp(name=""):
    o, d = RAYS.get(name, (O, D_RAW))
    d = [mp.mpf(c) for c in d]
    n = mp.sqrt(sum(c * c for c in d))
    return [mp.mpf(c) for c in o], [c / n for c in d]


def _functions():
    """name → (φ(x), ∇φ(x)) in mpmath for three shapes with a simple first root on the ray."""

    def sph(x):
        return mp.sqrt(sum(c * c for c in x)) - 1

    def sph_g(x):
        n = mp.sqrt(sum(c * c for c in x))
        return [c / n for c in x]

    def alg(x):
        return sum(c * c for c in x) - 1

    def alg_g(x):
        return [2 * c for c in x]

    R, r = mp.mpf(1), mp.mpf("0.4")

    def tor(x):
        return mp.sqrt((mp.sqrt(x[0] ** 2 + x[1] ** 2) - R) ** 2 + x[2] ** 2) - r

    def tor_g(x):
        rho = mp.sqrt(x[0] ** 2 + x[1] ** 2)
        q = mp.sqrt((rho - R) ** 2 + x[2] ** 2)
        return [(rho - R) / q * x[0] / rho, (rho - R) / q * x[1] / rho, x[2] / q]

    return {"sphere SDF": (sph, sph_g), "algebraic sphere |x|²−1": (alg, alg_g), "torus SDF R=1 r=0.4": (tor, tor_g)}


def _along(phi, grad, name=""):
    o, d = _ray_mp(name)

    def g(t):
        return phi([o[i] + t * d[i] for i in range(3)])

    def dg(t):
        gr = grad([o[i] + t * d[i] for i in range(3)])
        return sum(gr[i] * d[i] for i in range(3))

    return g, dg


def _first_root(g, dg):
    """First sign change on a 1e-3 grid of [0, 6], bisected to 1e-12 and polished by 12 Newton steps at
    400 digits (quadratic convergence from 1e-12: error < 1e-380)."""
    ts = np.arange(0.0, 6.0, 1e-3)
    vals = np.array([float(g(mp.mpf(t))) for t in ts])
    k = int(np.argmax(np.sign(vals[:-1]) != np.sign(vals[1:])))
    with mp.workdps(400):
        lo, hi = mp.mpf(ts[k]), mp.mpf(ts[k + 1])
        t = bisection(g, lo, hi, 30)[-1]
        return newton(g, dg, t, 12)[-1]


def bisection(g, lo, hi, n):
    xs = []
    glo = g(lo)
    for _ in range(n):
        mid = (lo + hi) / 2
        gm = g(mid)
        if (gm > 0) == (glo > 0):
            lo, glo = mid, gm
        else:
            hi = mid
        xs.append((lo + hi) / 2)
    return xs


def newton(g, dg, x, n):
    xs = []
    for _ in range(n):
        x = x - g(x) / dg(x)
        xs.append(x)
    return xs


def secant(g, x0, x1, n):
    xs = []
    g0, g1 = g(x0), g(x1)
    for _ in range(n):
        if g1 == g0:
            break
        x0, x1 = x1, x1 - g1 * (x1 - x0) / (g1 - g0)
        g0, g1 = g1, g(x1)
        xs.append(x1)
    return xs


def observed_order(errs) -> float:
    e = np.array([float(mp.log10(v)) if v > 0 else -np.inf for v in errs])
    ok = (e < -6) & (e > -280)
    pairs = ok[:-1] & ok[1:]
    if pairs.sum() < 2:
        raise ValueError("fewer than 2 iterate pairs in the asymptotic range")
    a, b = e[:-1][pairs], e[1:][pairs]
    return float(np.polyfit(a, b, 1)[0])


@LEDGER.claim(
    "6a",
    statement="near a simple root bisection converges linearly with ratio 1/2, Newton quadratically (order 2) "
    "and the secant method with order (1+√5)/2 ≈ 1.618",
    equation="slides 'Ray marching in implicit surfaces' (bisection, Newton, secant update)",
    how_checked="g(t)=φ(o+td) on one oblique ray for a sphere SDF, x²+y²+z²−1 and a torus SDF, iterated in "
    "mpmath (300 digits) from a bracket of width 0.5 / a start 0.05 before the root / starts 0.1 and 0.05 "
    "before it; a trial (method × function) holds if the fitted order is within 0.1 of the claim "
    "(bisection: fitted ratio within 0.05 of 1/2)",
    scope="simple roots (φ'(t*) ≠ 0), iterates in the asymptotic range, exact arithmetic (300 digits) so that rounding does not cut the sequence short",
)
def check_orders(ctx):
    trials, key, curves = [], {}, []
    with mp.workdps(300):
        for name, (phi, grad) in _functions().items():
            g, dg = _along(phi, grad, name)
            root = _first_root(g, dg)
            err = lambda xs: [abs(x - root) for x in xs]  # noqa: E731
            eb = err(bisection(g, root - mp.mpf("0.3"), root + mp.mpf("0.2"), 200 if ctx.quick else 900))
            en = err(newton(g, dg, root - mp.mpf("0.05"), 14))
            es = err(secant(g, root - mp.mpf("0.1"), root - mp.mpf("0.05"), 20))
            lb = np.array([float(mp.log(v)) for v in eb])
            ratio = float(np.exp(np.polyfit(np.arange(lb.size), lb, 1)[0]))
            qn, qs = observed_order(en), observed_order(es)
            trials += [
                Trial(f"bisection on {name}", abs(ratio - 0.5) <= 0.05, {"ratio": ratio}),
                Trial(f"Newton on {name}", abs(qn - 2) <= 0.1, {"order": qn}),
                Trial(f"secant on {name}", abs(qs - GOLDEN) <= 0.1, {"order": qs}),
            ]
            key[f"{name}: bisection ratio"] = ratio
            key[f"{name}: Newton order"] = qn
            key[f"{name}: secant order"] = qs
            curves.append((name, eb, en, es))
        # contrast outside the claim's scope: a tangent ray (double root) — orders drop to 1
        o, d = _ray_mp()
        # ray tangent to the sphere: shift the origin so the impact parameter is exactly 1
        b = [o[i] - sum(o[j] * d[j] for j in range(3)) * d[i] for i in range(3)]
        nb = mp.sqrt(sum(c * c for c in b))
        o_t = [o[i] - b[i] + b[i] / nb for i in range(3)]
        alg = _functions()["algebraic sphere |x|²−1"]
        gt = lambda t: alg[0]([o_t[i] + t * d[i] for i in range(3)])  # noqa: E731
        dgt = lambda t: sum(c * d[i] for i, c in enumerate(alg[1]([o_t[j] + t * d[j] for j in range(3)])))  # noqa: E731
        t_star = -sum(o_t[i] * d[i] for i in range(3))
        en2 = [abs(x - t_star) for x in newton(gt, dgt, t_star - mp.mpf("0.05"), 60)]
        key["tangent ray (double root) x²+y²+z²−1: Newton error ratio"] = float(en2[-1] / en2[-2])

    fig, axes = figure(3, 1, 4.2, 3.6)
    for ax, (name, eb, en, es) in zip(axes, curves):
        for lab, e in (("bisection", eb[:60]), ("Newton", en), ("secant", es)):
            ax.semilogy(range(1, len(e) + 1), [max(float(v), 1e-300) for v in e], ".-", label=lab)
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("iteration")
        ax.set_ylabel("|t_n − t*| (length units, 300-digit arithmetic)")
        ax.legend(fontsize=7)
    return Evidence(trials, key, fig)


# -- 6b: secant without good initial guesses ---------------------------------------------------------


def _g64(kind):
    o, d = RAYS.get(kind, (O, D_RAW))
    o = np.array(o)
    d = np.array(d) / np.linalg.norm(d)
    if kind == "sphere SDF":
        f = lambda x: np.linalg.norm(x, axis=-1) - 1  # noqa: E731
    elif kind == "algebraic sphere |x|²−1":
        f = lambda x: np.sum(x * x, -1) - 1  # noqa: E731
    else:
        f = lambda x: np.hypot(np.hypot(x[..., 0], x[..., 1]) - 1.0, x[..., 2]) - 0.4  # noqa: E731
    return lambda t: f(o + np.asarray(t)[..., None] * d)


def _all_roots(g, lo=-10.0, hi=20.0, h=1e-3):
    ts = np.arange(lo, hi, h)
    v = g(ts)
    k = np.flatnonzero(np.sign(v[:-1]) != np.sign(v[1:]))
    a, b = ts[k], ts[k + 1]
    for _ in range(60):
        m = (a + b) / 2
        s = np.sign(g(m)) == np.sign(g(a))
        a, b = np.where(s, m, a), np.where(s, b, m)
    return (a + b) / 2


def secant64(g, t0, t1, n=100):
    """Vectorised float64 secant; returns final iterate (nan where it broke down)."""
    g0, g1 = g(t0), g(t1)
    for _ in range(n):
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            # g1 == g0 (converged, or a flat secant) stops the update: the iterate stays where it is
            t2 = np.where(g1 != g0, t1 - g1 * (t1 - t0) / (g1 - g0), t1)
        t0, g0 = t1, g1
        t1 = np.where(np.isfinite(t2) & (np.abs(t2) < 1e6), t2, np.nan)
        g1 = g(t1)
    return t1


@LEDGER.claim(
    "6b",
    statement="the secant method does not guarantee convergence and usually requires good initial guesses",
    equation="slide 'Ray marching in implicit surfaces: secant', remark",
    how_checked="float64 secant (100 steps) from every pair (t0,t1) of a grid on [0,6]² for g(t)=φ(o+td) "
    "(sphere SDF, x²+y²+z²−1, torus SDF); outcome: first hit (|t−t*|≤1e-9), another root, or no "
    "convergence; trials: 'arbitrary guesses can fail' holds if some pairs miss the first hit; 'good "
    "guesses work' holds if every pair within 0.05 of the first hit (both before it) converges to it",
    scope="the secant method from arbitrary starting pairs along a ray (both parts: no guarantee; good guesses work)"
)
def check_secant_guesses(ctx):
    m = 121 if ctx.quick else 601
    grid = np.linspace(0.0, 6.0, m)
    T0, T1 = np.meshgrid(grid, grid)
    trials, key, imgs = [], {}, []
    for kind in ("sphere SDF", "algebraic sphere |x|²−1", "torus SDF R=1 r=0.4"):
        g = _g64(kind)
        roots = _all_roots(g)
        first = roots[roots > 0].min()
        tf = secant64(g, T0.ravel(), T1.ravel())
        dist = np.abs(tf[:, None] - roots[None, :])
        to_first = np.abs(tf - first) <= 1e-9
        to_other = ~to_first & (np.nanmin(np.where(np.isfinite(dist), dist, np.inf), axis=1) <= 1e-9)
        fail = ~to_first & ~to_other
        offdiag = T0.ravel() != T1.ravel()  # t0 = t1 is no secant at all
        frac_first = float(to_first[offdiag].mean())
        trials.append(Trial(f"{kind}: arbitrary guesses in [0,6]² can miss the first hit",
                            bool((~to_first[offdiag]).any()),
                            {"to_first": frac_first, "to_other_root": float(to_other[offdiag].mean()),
                             "no_convergence": float(fail[offdiag].mean())}))
        near = np.linspace(first - 0.05, first - 1e-3, 25)
        N0, N1 = np.meshgrid(near, near)
        sel = N0.ravel() != N1.ravel()
        tn = secant64(g, N0.ravel()[sel], N1.ravel()[sel])
        ok_near = float(np.mean(np.abs(tn - first) <= 1e-9))
        trials.append(Trial(f"{kind}: guesses within 0.05 before the first hit converge to it", ok_near == 1.0,
                            {"fraction": ok_near}))
        key[f"{kind}: roots on the line"] = np.round(roots, 6).tolist()
        key[f"{kind}: fraction of [0,6]² pairs → first hit / other root / none"] = [
            round(frac_first, 4), round(float(to_other[offdiag].mean()), 4), round(float(fail[offdiag].mean()), 4)]
        code = np.where(to_first, 0, np.where(to_other, 1, 2)).reshape(T0.shape)
        imgs.append((kind, code, first))
    fig, axes = figure(3, 1, 3.8, 3.6)
    from matplotlib.colors import ListedColormap

    cmap = ListedColormap(["#2a9d8f", "#e9c46a", "#e76f51"])
    for ax, (kind, code, first) in zip(axes, imgs):
        ax.imshow(code, origin="lower", extent=(0, 6, 0, 6), cmap=cmap, vmin=0, vmax=2, interpolation="nearest")
        ax.axvline(first, color="k", lw=0.6)
        ax.axhline(first, color="k", lw=0.6)
        ax.set_title(f"{kind}\ngreen: first hit, yellow: other root, red: none", fontsize=7)
        ax.set_xlabel("t0 (length units)")
        ax.set_ylabel("t1 (length units)")
    return Evidence(trials, key, fig)
