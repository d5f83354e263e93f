"""Samples to a colour error target: how many samples per ray each volume sampler needs to come
within a target of the rendering integral (``python -m bench sampling``).

For a case and a density model (NeRF density σ = s·sigmoid(−sφ), s = 50 by default), the
reference is the continuous rendering integral C = ∫ T σ ρ dt of :func:`bench.run.references.exact_color`
(adaptive quadrature, error bound ≈ 1e-11) on ``max_rays`` rays strided through the case
(:func:`bench.run.references.reference_rays`).  Each sampler (``volume_<density>_<sampler>``, numpy
backend, no early termination) renders those rays with N samples; its error at N is the largest
colour error ‖C_N − C‖₂ over the rays of a set: ``all`` the reference rays, or ``hits`` those
whose exact first hit exists (the near-surface ``band`` sampler needs that hit t̂ and renders
colour 0 without one, so on rays passing just outside the surface, where the integral is not
small, it cannot converge at all).

The search: N = ``n_min``, 2·n_min, … ≤ ``n_max`` until the error is ≤ the target, then bisection
between that N and the one before it.  The error of the stratified (random jitter) and importance
samplers is not monotone in N, so the N found is the smallest on that search path, not
necessarily the smallest overall.  ``samples`` counts the φ samples per ray a sampler plans: N,
plus ``n_coarse`` for importance sampling (its coarse pass); ``x_fewer_than_uniform`` is uniform's
samples over the sampler's for the same case, ray set and target.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
import pandas as pd

DEFAULT_CASES = ("sphere.camera.64x64", "torus.camera.32x32")
DEFAULT_TARGETS = (1e-2, 1e-3, 1e-4)
#: (label, sampler, knobs) of the samplers compared
VARIANTS = (("uniform", "uniform", {}), ("stratified", "stratified", {}), ("band Δ=0.1", "band", {"delta": 0.1}),
            ("band Δ=0.3", "band", {"delta": 0.3}), ("band Δ=0.5", "band", {"delta": 0.5}),
            ("importance", "importance", {}))


class ColourErrors:
    """Per-ray colour errors ‖C_N − C‖₂ of each sampler at N samples on the reference rays of one
    case (memoised: each (sampler, N) is rendered once)."""

    def __init__(self, case, density: str = "nerf", sharpness: float = 50.0, max_rays: int = 64, backend: str = "numpy",
                 disk=None):
        from impls import METHODS, registry

        from ..run.references import ReferenceOptions, exact_color, reference_rays

        self.case, self.density, self.sharpness = case, density, float(sharpness)
        self.backend = registry.resolve(backend)
        if isinstance(self.backend, registry.Unavailable):
            raise ValueError(f"backend {backend!r} is unavailable: {self.backend.reason}")
        cache = {"_options": ReferenceOptions(max_rays=max_rays, disk=disk, timeout_s=0)}
        colors, self.reference_bound = exact_color(case, METHODS[f"volume_{density}_uniform"],
                                                   {"sharpness": self.sharpness}, cache)
        self.idx = reference_rays(case.n_rays, max_rays)
        self.reference = colors[self.idx]
        self.t_hit = np.asarray(case.exact_t, np.float64)[self.idx]
        self.rays = {"all": np.ones(self.idx.size, bool), "hits": np.isfinite(self.t_hit)}
        self._memo: dict = {}

    def __call__(self, sampler: str, knobs: dict, n: int) -> np.ndarray:
        key = (sampler, tuple(sorted(knobs.items())), int(n))
        if key not in self._memo:
            c = self.case
            p = self.backend.prepare(f"volume_{self.density}_{sampler}", c.scene, c.origins[self.idx],
                                     c.directions[self.idx], t_min=c.t_min, t_max=c.t_max, color=c.color_field,
                                     t_hit=self.t_hit if sampler == "band" else None, n_samples=int(n),
                                     sharpness=self.sharpness, t_threshold=0.0, **knobs)
            got = np.asarray(p.result(p.run()).outputs["color"], np.float64)
            err = np.linalg.norm(got - self.reference, axis=1)
            self._memo[key] = np.where(np.isfinite(err), err, np.inf)
        return self._memo[key]


def smallest_n(error: Callable[[int], float], target: float, n_min: int = 4, n_max: int = 4096,
               bisect: bool = True) -> tuple[int | None, float, float]:
    """(N, error at N, smallest error seen) for the search of the module docstring; N is None when
    no N ≤ ``n_max`` on the doubling path reaches ``target``."""
    prev, n, best = None, n_min, math.inf
    while n <= n_max:
        e = error(n)
        best = min(best, e)
        if e <= target:
            break
        prev, n = n, 2 * n
    else:
        return None, math.nan, best
    found, found_e = n, e
    if bisect and prev is not None:
        lo, hi = prev, n
        while hi - lo > 1:
            mid = (lo + hi) // 2
            em = error(mid)
            best = min(best, em)
            if em <= target:
                hi, found_e = mid, em
            else:
                lo = mid
        found = hi
    return found, found_e, best


def check_arguments(case_ids, targets, sharpness: float) -> None:
    """ValueError naming the argument (``--case``, ``--targets``, ``--sharpness``) when
    :func:`sampling_table` could not run on them: no case, a case without a colour field ρ,
    targets that are not finite and > 0, a sharpness that is not finite and > 0 (the density
    s·sigmoid(−sφ) needs one).  Checked before anything costly runs."""
    from reference.cases import get_case

    if not list(case_ids):
        raise ValueError("--case: no case given; name case ids, e.g. sphere.camera.64x64")
    if not list(targets) or not all(math.isfinite(t) and t > 0 for t in targets):
        raise ValueError(f"--targets: {list(targets)} must be finite numbers > 0, e.g. 1e-2,1e-3")
    if not (math.isfinite(sharpness) and sharpness > 0):
        raise ValueError(f"--sharpness: must be a finite number > 0 (the density's s), got {sharpness}")
    for cid in case_ids:
        try:
            case = get_case(cid)
        except (KeyError, ValueError) as exc:
            raise ValueError(f"--case: {exc}") from None
        if getattr(case, "color_field", None) is None:
            raise ValueError(f"--case: {cid} has no colour field ρ, so it has no rendering integral to sample "
                             "towards; pick a case with one (e.g. sphere.camera.64x64)")


def sampling_table(case_ids=DEFAULT_CASES, targets=DEFAULT_TARGETS, *, density: str = "nerf",
                   sharpness: float = 50.0, variants=VARIANTS, n_min: int = 4, n_max: int = 4096, bisect: bool = True,
                   max_rays: int = 64, backend: str = "numpy", disk=None,
                   progress: Callable[[str], None] | None = None, every_s: float = 30.0) -> pd.DataFrame:
    """One row per case × ray set × sampler × target (columns in the module docstring).
    ``progress(line)``: a line as each stage starts (a case's reference integral, each sampler's
    search) and at least every ``every_s`` seconds while one runs (:class:`bench.run.heartbeat.Heartbeat`).
    Arguments are checked first (:func:`check_arguments`); a reference the case cannot give is a
    :class:`bench.run.references.NotApplicable` naming the case."""
    from reference.cases import get_case

    from ..run.heartbeat import Heartbeat

    check_arguments(case_ids, targets, sharpness)
    with Heartbeat(progress, every_s) as beat:
        return _table(case_ids, targets, density, sharpness, variants, n_min, n_max, bisect, max_rays, backend, disk,
                      beat, get_case)


def _table(case_ids, targets, density, sharpness, variants, n_min, n_max, bisect, max_rays, backend, disk, beat,
           get_case) -> pd.DataFrame:
    """:func:`sampling_table`'s work, each stage announced on ``beat``."""
    from ..run.references import reference_rays

    rows = []
    for k, cid in enumerate(case_ids, 1):
        case = get_case(cid)
        beat.stage(f"sampling {cid} ({k}/{len(case_ids)}): the rendering integral on "
                   f"{reference_rays(case.n_rays, max_rays).size} rays ({density}, s = {sharpness:g}; minutes for "
                   "a mesh or a kinked field, cached in reports/.refcache)")
        errs = ColourErrors(case, density, sharpness, max_rays, backend, disk)
        for rayset, mask in errs.rays.items():
            if not mask.any():
                continue
            for label, sampler, knobs in variants:
                beat.stage(f"sampling {cid} · {rayset} · {label}: searching N for {len(targets)} target(s)")
                extra = int(knobs.get("n_coarse", 32)) if sampler == "importance" else 0
                for target in targets:
                    def error(n, sampler=sampler, knobs=knobs, mask=mask):
                        return float(np.max(errs(sampler, knobs, n)[mask]))

                    n, e_n, best = smallest_n(error, target, n_min, n_max, bisect)
                    rows.append({"case_id": cid, "rays": rayset, "n_rays": int(mask.sum()), "sampler": label,
                                 "target": target, "N": n, "samples": None if n is None else n + extra,
                                 "error_at_N": e_n, "best_error": best, "density": density, "sharpness": sharpness,
                                 "reference_bound": errs.reference_bound})
                beat.say(f"sampling {cid} · {rayset} · {label}: done")
    df = pd.DataFrame(rows)
    uni = df[df["sampler"] == "uniform"].set_index(["case_id", "rays", "target"])["samples"]
    key = list(zip(df["case_id"], df["rays"], df["target"]))
    u = np.array([uni.get(k, np.nan) for k in key], dtype=float)
    df["x_fewer_than_uniform"] = u / df["samples"].astype(float)
    return df


def markdown(df: pd.DataFrame) -> str:
    """The table as markdown: a row per case, ray set and sampler; per target the samples per ray
    (``>n_max`` where not reached, with the smallest error seen) and the factor fewer than uniform."""
    lines = []
    targets = sorted(df["target"].unique(), reverse=True)
    head = ["case", "rays", "sampler"] + [f"≤ {t:g}: samples (× fewer than uniform)" for t in targets]
    lines.append("| " + " | ".join(head) + " |")
    lines.append("|" + "---|" * len(head))
    for (cid, rayset, sampler), g in df.groupby(["case_id", "rays", "sampler"], sort=False):
        g = g.set_index("target")
        cells = []
        for t in targets:
            r = g.loc[t]
            if r["samples"] is None or not np.isfinite(float(r["samples"])):
                cells.append(f"not reached (best {r['best_error']:.3g})")
            else:
                x = r["x_fewer_than_uniform"]
                cells.append(f"{int(r['samples'])}" + (f" ({x:.2g}×)" if np.isfinite(x) else ""))
        lines.append(f"| {cid} | {rayset} ({int(g['n_rays'].iloc[0])}) | {sampler} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


FILE = "sampling.csv"


def section_md(run_dir) -> list[str]:
    """The report's section for a run directory holding :data:`FILE` (written by
    ``python -m bench sampling --out RUN_DIR``); [] without one."""
    from pathlib import Path

    path = Path(run_dir) / FILE
    if not path.is_file():
        return []
    df = pd.read_csv(path)
    df["samples"] = df["samples"].astype(object).where(df["samples"].notna(), None)
    r0 = df.iloc[0]
    return ["## Samples to a colour error target", "",
            f"Samples per ray each volume sampler needs for a colour error ≤ the target against the rendering "
            f"integral ({r0['density']} density, s = {r0['sharpness']:g}; max over the rays of the set; `bench/studies/sampling.py`).",
            "", markdown(df), ""]
