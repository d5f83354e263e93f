"""Claim 4: MLPs are Lipschitz with L ≤ Π‖W_i‖₂ · sup|σ'| (lecture eqs. 2–6), "the spectral norm equals
the largest eigenvalue", and sphere tracing with step f/L on the MLP never passes through the surface.

The MLP comes from :func:`adapters.mlp_field` (SWITCH to the reference MLP with stored weights).
‖W‖₂ is the largest singular value (``numpy.linalg.norm(W, 2)``, LAPACK SVD).
"""

from __future__ import annotations

import numpy as np

from . import adapters
from .figures import figure
from .ledger import LEDGER, Evidence, Trial
from .tracing import camera_rays, dense_first_hit, sphere_trace_signed

SEEDS = (7, 8, 9)


def lipschitz_bound(net: adapters.MLP) -> float:
    """Π‖W_i‖₂ · (sup|σ'|)^(hidden layers) — the lecture's eq. 4–5 composed over the layers."""
    return float(np.prod([np.linalg.norm(W, 2) for W in net.weights]) * net.sup_dact ** (len(net.weights) - 1))


def _empirical(net, rng, n):
    """Largest |f(x)−f(y)|/|x−y| over random pairs (far and close) and largest |∇f| at random points."""
    x = rng.uniform(-2, 2, (n, 3))
    y = rng.uniform(-2, 2, (n, 3))
    close = x + rng.normal(0, 1e-3, (n, 3))
    r_far = np.abs(net.value(x) - net.value(y)) / np.linalg.norm(x - y, axis=-1)
    r_close = np.abs(net.value(x) - net.value(close)) / np.linalg.norm(x - close, axis=-1)
    g = np.linalg.norm(net.grad(x), axis=-1)
    return float(max(r_far.max(), r_close.max())), float(g.max()), r_close


@LEDGER.claim(
    "4a",
    statement="an MLP is Lipschitz continuous with L ≤ Π‖W_i‖ · sup|σ'| (bounded activation derivatives)",
    equation="eqs. (2)–(6), slide 'MLP is Lipschitz Continuous'",
    how_checked="seeded tanh MLPs 3-32-32-1 (stand-in for the stored MLP); largest |f(x)−f(y)|/|x−y| over "
    "random far and close (|x−y|≈1e-3) pairs in [−2,2]³ and largest |∇f| (backprop) at random points; a trial "
    "(network) holds if both are ≤ the bound",
)
def check_bound(ctx):
    rng = np.random.default_rng(ctx.seed + 4)
    n = 20_000 if ctx.quick else 200_000
    trials, key, hists = [], {}, []
    for seed in SEEDS:
        net = adapters.mlp_field(seed)
        L = lipschitz_bound(net)
        emp, gmax, ratios = _empirical(net, rng, n)
        trials.append(Trial(f"tanh MLP seed {seed}", emp <= L and gmax <= L,
                            {"bound": L, "max_ratio": emp, "max_grad": gmax}))
        key[f"seed {seed}: bound"] = L
        key[f"seed {seed}: max |∇f|"] = gmax
        key[f"seed {seed}: tightness max|∇f|/bound"] = gmax / L
        hists.append((seed, ratios / L))
    fig, (ax,) = figure(1, 1, 6.5, 4)
    for seed, r in hists:
        ax.hist(r, bins=80, histtype="step", label=f"seed {seed}")
    ax.axvline(1.0, color="k", ls=":", label="bound (ratio 1)")
    ax.set_xlabel("|f(x)−f(y)|/|x−y| ÷ Π‖W_i‖·sup|σ'| (dimensionless), close pairs")
    ax.set_ylabel("pairs")
    ax.set_yscale("log")
    ax.legend(fontsize=7)
    return Evidence(trials, key, fig)


def _matrices(rng):
    A = rng.normal(size=(5, 5))
    Q, _ = np.linalg.qr(A)
    psd = Q @ np.diag([3.0, 2.0, 1.0, 0.5, 0.1]) @ Q.T
    indef = Q @ np.diag([-3.0, 2.0, 1.0, 0.5, 0.1]) @ Q.T
    net = adapters.mlp_field(SEEDS[0])
    return [
        ("symmetric positive semidefinite 5×5", psd),
        ("symmetric indefinite 5×5 (eigenvalues −3, 2, 1, .5, .1)", indef),
        ("the MLP's hidden 32×32 weight (non-symmetric)", net.weights[1]),
        ("Jordan block [[0,1],[0,0]]", np.array([[0.0, 1.0], [0.0, 0.0]])),
        ("the MLP's first-layer 32×3 weight (rectangular)", net.weights[0]),
    ]


@LEDGER.claim(
    "4b",
    statement="the spectral norm ‖W‖ = max ‖Wx‖/‖x‖ equals the largest eigenvalue",
    equation="eq. (6) and the remark below it",
    how_checked="‖W‖₂ (largest singular value, SVD) against the largest eigenvalue read charitably as the "
    "spectral radius max|λ| (and also as the largest real eigenvalue); a trial (matrix) holds if "
    "|‖W‖₂ − max|λ|| ≤ 1e-12‖W‖₂; rectangular matrices have no eigenvalues and fail",
)
def check_spectral(ctx):
    rng = np.random.default_rng(ctx.seed + 5)
    trials, key, bars = [], {}, []
    for name, W in _matrices(rng):
        s = float(np.linalg.norm(W, 2))
        # the identity that does hold for every W: ‖W‖₂ = √λ_max(WᵀW)
        key[f"{name}: |‖W‖₂ − √λmax(WᵀW)|"] = abs(s - float(np.sqrt(np.linalg.eigvalsh(W.T @ W).max())))
        if W.shape[0] != W.shape[1]:
            trials.append(Trial(name, False, {"spectral_norm": s, "eigenvalues": "undefined"}))
            key[f"{name}: ‖W‖₂"] = s
            bars.append((name, s, np.nan, np.nan))
            continue
        ev = np.linalg.eigvals(W)
        rho, lmax = float(np.abs(ev).max()), float(ev.real.max())
        trials.append(Trial(name, abs(s - rho) <= 1e-12 * s, {"spectral_norm": s, "max_abs_eig": rho,
                                                              "max_real_eig": lmax}))
        key[f"{name}: ‖W‖₂"] = s
        key[f"{name}: max|λ|"] = rho
        key[f"{name}: max λ"] = lmax
        bars.append((name, s, rho, lmax))
    fig, (ax,) = figure(1, 1, 7.5, 4)
    y = np.arange(len(bars))
    ax.barh(y - 0.25, [b[1] for b in bars], 0.25, label="‖W‖₂ (largest singular value)")
    ax.barh(y, [b[2] for b in bars], 0.25, label="max |λ|")
    ax.barh(y + 0.25, [b[3] for b in bars], 0.25, label="max real λ")
    ax.set_yticks(y, [b[0] for b in bars], fontsize=7)
    ax.set_xlabel("value (dimensionless)")
    ax.legend(fontsize=7)
    return Evidence(trials, key, fig)


@LEDGER.claim(
    "4c",
    statement="sphere tracing the MLP with step f/L (L = Π‖W_i‖·sup|σ'|) never passes through the surface",
    equation="eqs. (2)–(6) with slide 'Sphere Tracing'",
    how_checked="a pinhole grid of rays on each seeded MLP; steps t ← t + |f|/L from t=0 (= the signed step on "
    "rays starting outside); reference first "
    "hit by dense sampling (h=1e-3) + bisection; a trial (network × step) holds if no iterate goes beyond the "
    "reference first hit (+1e-9) and it never stops where there is no hit (rays that do not converge in "
    "20000 steps are counted, not failed); steps with L=1 and with the empirical max |∇f| are reported for contrast",
)
def check_trace(ctx):
    n_side = 6 if ctx.quick else 16
    o, d = camera_rays(n_side, eye=(0.4, 0.3, 4.0), fov_deg=40.0)
    trials, key, rows = [], {}, []
    rng = np.random.default_rng(ctx.seed + 6)
    for seed in SEEDS[: 1 if ctx.quick else 3]:
        net = adapters.mlp_field(seed)
        L = lipschitz_bound(net)
        _, gmax, _ = _empirical(net, rng, 5000)
        t_ref = dense_first_hit(net.value, o, d, t_max=8.0, h=1e-3)
        hit = np.isfinite(t_ref)
        key[f"seed {seed}: rays starting inside (f(o) ≤ 0)"] = int(np.sum(net.value(o) <= 0))
        # only the bound's step is the claim; L=1 and the empirical max|∇f| are contrast (key numbers)
        for label, lip, is_claim in ((f"bound L={L:.3g}", L, True), (f"empirical max|∇f|={gmax:.3g}", gmax, False),
                                     ("L=1", 1.0, False)):
            # |f|/L steps: the lecture's signed step on rays starting outside (f > 0 until the first crossing
            # when the step does not overshoot), and a forward march to the exit on rays that start inside
            r = sphere_trace_signed(net.value, o, d, lipschitz=lip, tol=1e-9, max_steps=20_000, t_max=8.0,
                                    abs_step=True)
            with np.errstate(invalid="ignore"):
                passed = hit & (r.t_furthest > t_ref + 1e-9 * (1 + t_ref))
                wrong = r.converged & ~(np.abs(r.t - t_ref) <= 1e-6)  # stopped where there is no first hit
            missed = hit & ~r.converged
            nums = {"rays_hit": int(hit.sum()), "passed_through": int(passed.sum()), "wrong_root": int(wrong.sum()),
                    "not_converged": int(missed.sum()), "mean_steps": float(r.iterations.mean())}
            if is_claim:
                trials.append(Trial(f"MLP seed {seed}, step f/L with the bound", not (passed.any() or wrong.any()), nums))
            key[f"seed {seed} {label}: passed/hit rays"] = f"{int(passed.sum())}/{int(hit.sum())}"
            key[f"seed {seed} {label}: not converged in 20000 steps"] = int(missed.sum())
            key[f"seed {seed} {label}: mean steps"] = float(r.iterations.mean())
            rows.append((f"s{seed} {label.split('=')[0]}", passed.sum() / max(hit.sum(), 1), r.iterations.mean()))
    fig, axes = figure(2, 1, 5.0, 4)
    names = [r[0] for r in rows]
    axes[0].barh(names, [r[1] for r in rows])
    axes[0].set_xlabel("fraction of hitting rays that passed through the surface")
    axes[1].barh(names, [r[2] for r in rows])
    axes[1].set_xscale("log")
    axes[1].set_xlabel("mean sphere-tracing steps per ray")
    for ax in axes:
        ax.tick_params(axis="y", labelsize=7)
    return Evidence(trials, key, fig)
