"""Accuracy of a root finder's depths against the exact first hit.

Error per ray e = |t − t*| where t* is the exact depth; a ray that both the method and the
reference call a miss has e = 0, a false hit or false miss has e = inf (so a max error is
honest: it cannot hide a wrong answer).  Also reported in units of the dtype's eps relative to
the depth: e / (eps · max(|t*|, 1)).
"""

from __future__ import annotations

import numpy as np

from impls.protocol import RayResult, Status


def depth_errors(res: RayResult, exact_t: np.ndarray) -> np.ndarray:
    exact_hit = np.isfinite(exact_t)
    got_hit = (res.status == Status.CONVERGED) & np.isfinite(res.t)
    e = np.full(exact_t.shape, np.inf)
    both = exact_hit & got_hit
    e[both] = np.abs(res.t[both] - exact_t[both])
    e[~exact_hit & ~got_hit] = 0.0
    return e


def summarize(res: RayResult, exact_t: np.ndarray, dtype: str) -> dict:
    e = depth_errors(res, exact_t)
    exact_hit = np.isfinite(exact_t)
    got_hit = res.status == Status.CONVERGED
    eps = float(np.finfo(dtype).eps)
    scale = np.where(exact_hit, np.maximum(np.abs(np.where(exact_hit, exact_t, 1.0)), 1.0), 1.0)
    finite = e[np.isfinite(e)]
    return {
        "error_max": float(e.max()) if e.size else 0.0,
        "error_p99": float(np.percentile(e, 99, method="inverted_cdf")) if e.size else 0.0,
        "error_median": float(np.percentile(e, 50, method="inverted_cdf")) if e.size else 0.0,
        "error_max_finite": float(finite.max()) if finite.size else float("nan"),
        "error_max_eps": float((e / (eps * scale)).max()) if e.size else 0.0,
        "n_false_hit": int(np.sum(got_hit & ~exact_hit)),
        "n_false_miss": int(np.sum(~got_hit & exact_hit)),
        "evals_per_ray": float(res.evals.mean()),
        "evals_p99": float(np.percentile(res.evals, 99)),
        "evals_max": int(res.evals.max()),
        "iterations_max": int(res.iterations.max()),
    }
