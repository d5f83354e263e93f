"""Claim 4: MLPs are Lipschitz with L ≤ Π‖W_i‖₂ · sup|σ'| (lecture eqs. 2–6), "the spectral norm equals
the largest eigenvalue", and sphere tracing with step f/L on the MLP never passes through the surface.

The MLP is the project's stored-weight reference field (:class:`reference.MLPField`, 3-16-16-1 with
σ(z) = z/√(1 + z²), sup|σ'| = 1; :func:`adapters.mlp_field`).  ‖W‖₂ is the largest singular value
(``numpy.linalg.norm(W, 2)``, LAPACK SVD); the bound is recomputed here from the lecture's formula and
compared with the reference's own ``lipschitz_bound``.
"""

from __future__ import annotations

import numpy as np

from . import adapters
from .figures import figure
from .ledger import LEDGER, Evidence, Trial
from .tracing import camera_rays, sphere_trace_signed

SUP_DACT = 1.0  # sup|σ'| of σ(z) = z/√(1 + z²): σ'(z) = (1 + z²)^(−3/2) ≤ 1, equality at z = 0
LAYERS = ("W1", "W2", "W3")
NET_NAME = "stored MLP 3-16-16-1, σ(z)=z/√(1+z²)"


def lipschitz_bound(net) -> float:
    """Π‖W_i‖₂ · (sup|σ'|)^(hidden layers) — the lecture's eq. 4–5 composed over the layers."""
    return float(np.prod([np.linalg.norm(net.weights[k], 2) for k in LAYERS]) * SUP_DACT ** (len(LAYERS) - 1))


def _empirical(net, rng, n, half=2.0):
    """Largest |f(x)−f(y)|/|x−y| over random pairs (far and close) in [−half, half]³ and largest |∇f| at
    random points (the reference's closed-form backpropagation)."""
    x = rng.uniform(-half, half, (n, 3))
    y = rng.uniform(-half, half, (n, 3))
    close = x + rng.normal(0, 1e-3, (n, 3))
    r_far = np.abs(net.value(x) - net.value(y)) / np.linalg.norm(x - y, axis=-1)
    r_close = np.abs(net.value(x) - net.value(close)) / np.linalg.norm(x - close, axis=-1)
    g = np.linalg.norm(net.jet(x)[1], axis=-1)
    return float(max(r_far.max(), r_close.max())), float(g.max()), r_close


@LEDGER.claim(
    "4a",
    statement="an MLP is Lipschitz continuous with L ≤ Π‖W_i‖ · sup|σ'| (bounded activation derivatives)",
    equation="eqs. (2)–(6), slide 'MLP is Lipschitz Continuous'",
    how_checked="the stored reference MLP 3-16-16-1 (σ(z)=z/√(1+z²)); bound Π‖W_i‖₂ by SVD; largest "
    "|f(x)−f(y)|/|x−y| over random far and close (|x−y|≈1e-3) pairs and largest |∇f| (backprop) at random "
    "points; a trial (sampling box [−2,2]³ or [−20,20]³) holds if both are ≤ the bound",
    scope="any MLP whose activations have bounded derivatives, anywhere in input space",
)
def check_bound(ctx):
    rng = np.random.default_rng(ctx.seed + 4)
    n = 20_000 if ctx.quick else 200_000
    trials, key, hists = [], {}, []
    net = adapters.mlp_field()
    L = lipschitz_bound(net)
    key["bound Π‖W_i‖₂ (lecture formula)"] = L
    key["|bound − reference lipschitz_bound|"] = abs(L - net.lipschitz_bound)
    for half in (2.0, 20.0):
        emp, gmax, ratios = _empirical(net, rng, n, half)
        trials.append(Trial(f"{NET_NAME}, pairs in [−{half:g},{half:g}]³", emp <= L and gmax <= L,
                            {"bound": L, "max_ratio": emp, "max_grad": gmax}))
        key[f"[−{half:g},{half:g}]³: max |∇f|"] = gmax
        key[f"[−{half:g},{half:g}]³: max ratio"] = emp
        key[f"[−{half:g},{half:g}]³: tightness max|∇f|/bound"] = gmax / L
        hists.append((f"pairs in [−{half:g},{half:g}]³", ratios / L))
    fig, (ax,) = figure(1, 1, 6.5, 4)
    for lab, r in hists:
        ax.hist(r, bins=80, histtype="step", label=lab)
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
    w = adapters.mlp_field().weights
    return [
        ("symmetric positive semidefinite 5×5", psd),
        ("symmetric indefinite 5×5 (eigenvalues −3, 2, 1, .5, .1)", indef),
        (f"the stored MLP's hidden {w['W2'].shape[0]}×{w['W2'].shape[1]} weight W2 (non-symmetric)", w["W2"]),
        ("Jordan block [[0,1],[0,0]]", np.array([[0.0, 1.0], [0.0, 0.0]])),
        (f"the stored MLP's first-layer {w['W1'].shape[0]}×{w['W1'].shape[1]} weight W1 (rectangular)", w["W1"]),
    ]


@LEDGER.claim(
    "4b",
    statement="the spectral norm ‖W‖ = max ‖Wx‖/‖x‖ equals the largest eigenvalue",
    equation="eq. (6) and the remark below it",
    how_checked="‖W‖₂ (largest singular value, SVD) against the largest eigenvalue read charitably as the "
    "spectral radius max|λ| (and also as the largest real eigenvalue); a trial (matrix) holds if "
    "|‖W‖₂ − max|λ|| ≤ 1e-12‖W‖₂; rectangular matrices have no eigenvalues and fail",
    scope="the weight matrices W_i of an MLP, i.e. any real matrix (square or not); named class: symmetric "
    "matrices, the eigenvalue read as the largest |λ|",
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
        sym = bool(np.allclose(W, W.T, rtol=0.0, atol=1e-13 * s))  # symmetric up to rounding of its construction
        trials.append(Trial(name, abs(s - rho) <= 1e-12 * s, {"spectral_norm": s, "max_abs_eig": rho,
                                                              "max_real_eig": lmax},
                            classes=("symmetric matrices (largest |λ|)",) if sym else ()))
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
    how_checked="a pinhole grid of rays on the stored reference MLP; steps t ← t + |f|/L from t=0 (= the signed "
    "step on rays starting outside); reference first hit from the certified numerical reference "
    "(reference.numerical: Lipschitz-certified bracketing + bisection); a trial (network × step) holds if no iterate goes beyond the "
    "reference first hit (+1e-9) and it never stops where there is no hit (rays that do not converge in "
    "20000 steps are counted, not failed); steps with L=1 and with the empirical max |∇f| are reported for contrast",
    scope="the stored MLP (any MLP of the lecture's form), rays from outside, the bound used as the step divisor",
)
def check_trace(ctx):
    n_side = 8 if ctx.quick else 24
    o, d = camera_rays(n_side, eye=(0.0, 0.0, 3.0), fov_deg=50.0)  # the catalog's mlp.camera view
    trials, key, rows = [], {}, []
    rng = np.random.default_rng(ctx.seed + 6)
    net = adapters.mlp_field()
    L = lipschitz_bound(net)
    _, gmax, _ = _empirical(net, rng, 5000)
    t_ref = net.first_hit(o, d, 0.0, 8.0)
    hit = np.isfinite(t_ref)
    key["rays starting inside (f(o) ≤ 0)"] = int(np.sum(net.value(o) <= 0))
    # only the bound's step is the claim; L=1 and the empirical max|∇f| are contrast (key numbers)
    for label, lip, is_claim in ((f"bound L={L:.3g}", L, True), (f"empirical max|∇f|={gmax:.3g}", gmax, False),
                                 ("L=1", 1.0, False)):
        # |f|/L steps: the lecture's signed step on rays starting outside (f > 0 until the first crossing
        # when the step does not overshoot), and a forward march to the exit on rays that start inside
        r = sphere_trace_signed(net.value, o, d, lipschitz=lip, tol=1e-9, max_steps=20_000, t_max=8.0,
                                abs_step=True)
        with np.errstate(invalid="ignore"):
            # (written so that a NaN iterate counts as passing through: it is not shown to stay before)
            passed = hit & ~(r.t_furthest <= t_ref + 1e-9 * (1 + t_ref))
            wrong = r.converged & ~(np.abs(r.t - t_ref) <= 1e-6)  # stopped where there is no first hit
        missed = hit & ~r.converged
        nums = {"rays_hit": int(hit.sum()), "passed_through": int(passed.sum()), "wrong_root": int(wrong.sum()),
                "not_converged": int(missed.sum()), "mean_steps": float(r.iterations.mean())}
        if is_claim:
            trials.append(Trial(f"{NET_NAME}, step f/L with the bound", not (passed.any() or wrong.any()), nums))
        key[f"{label}: passed/hit rays"] = f"{int(passed.sum())}/{int(hit.sum())}"
        key[f"{label}: not converged in 20000 steps"] = int(missed.sum())
        key[f"{label}: mean steps"] = float(r.iterations.mean())
        rows.append((label.split("=")[0], passed.sum() / max(hit.sum(), 1), r.iterations.mean()))
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
