"""The catalog sweep's (``bench run --case '*'``) one-process time, projected from a sample.

Method (docs/performance.md, "The catalog sweep on one process, projected from samples"): a
systematic sample of the sorted catalog (``python -m bench cases``: every ``every``-th case from
position ``offset``) is run in one process (``bench run --case ID,… --no-claims --no-stability``);
the configurations the whole sweep would run are counted per backend from the plan
(:func:`bench.run.plan.plan`) and :func:`bench.run.configuration.skip_reason`, without running
them; each backend's projected task time is its sample mean ``task_s`` per configuration run
(one per configuration key; a configuration counts as run when any of its rows is not skipped)
times its count in the whole plan.  The harness's own time per *planned* configuration (the
sample's wall time less its task time, over its planned configurations: planning, skipped
configurations, writing rows) is added per planned configuration of the sweep.

    T_sweep ≈ Σ_b n_b · mean_b(task_s)  +  N_planned · (wall − Σ task_s) / N_planned,sample

Two samples (offsets 0 and ``every``/2) bracket the estimate: their gap is its uncertainty.

    python -m bench.studies.sweep_projection sample [--every 8] [--offset 0]   # the case ids
    python -m bench.studies.sweep_projection project RUN_DIR [RUN_DIR …]        # the projection
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

CONFIG_KEY = ["case_id", "backend", "dtype", "method", "knob"]


def sample_ids(every: int = 8, offset: int = 0) -> list[str]:
    """Every ``every``-th case id of the sorted catalog, from position ``offset``."""
    if every < 1 or not 0 <= offset < every:
        raise ValueError(f"need every ≥ 1 and 0 ≤ offset < every, got every={every}, offset={offset}")
    from reference import catalog

    return sorted(c.id for c in catalog())[offset::every]


def sweep_counts() -> tuple[Counter, int]:
    """({backend: configurations the sweep runs}, configurations it plans) of ``--case '*'`` on
    the default suite and backends: planned as ``bench run`` plans it, a configuration counted as
    run when :func:`skip_reason` gives none (the reference answers it needs are computed, not the
    method).  Only the built-in backends (every registered one, unavailable ones skipped)."""
    from impls import registry

    from ..run.configuration import skip_reason
    from ..run.plan import plan
    from ..run.suites import get_suite

    backends = {}
    for spec in registry.default_ids():
        b = registry.resolve(spec)
        backends[spec if isinstance(b, registry.Unavailable) else b.id] = b
    cfgs = plan(get_suite("quick"), list(backends), "*", None, None)
    run = Counter(c.backend_id for c in cfgs if skip_reason(c, backends[c.backend_id]) is None)
    return run, len(cfgs)


def sample_rates(run_dir: Path) -> tuple[dict[str, float], float, int, int]:
    """({backend: mean task_s per configuration run}, wall s, planned configurations, task s)
    of a sample run."""
    from ..run.results import read_results

    run_dir = Path(run_dir)
    df = read_results(run_dir)
    env = json.loads((run_dir / "environment.json").read_text())
    wall = float(env.get("elapsed_s") or "nan")
    configs = df.drop_duplicates(CONFIG_KEY)
    ran = df[df["outcome"] != "skipped"].drop_duplicates(CONFIG_KEY)
    rates = ran.groupby("backend")["task_s"].mean().to_dict()
    return rates, wall, len(configs), float(configs["task_s"].fillna(0.0).sum())


def project(run_dirs: list[Path], counts: Counter, planned: int) -> str:
    """The projection of each sample run, as text."""
    lines = [f"the sweep plans {planned:,} configurations and runs {sum(counts.values()):,}: "
             + ", ".join(f"{b} {n:,}" for b, n in counts.most_common())]
    for run_dir in run_dirs:
        rates, wall, n_planned, task = sample_rates(run_dir)
        per_b = {b: counts[b] * rates.get(b, 0.0) for b in counts}
        missing = [b for b in counts if counts[b] and b not in rates]
        overhead = (wall - task) / n_planned if n_planned else 0.0
        total = sum(per_b.values()) + planned * overhead
        lines.append(f"{run_dir}: sample {n_planned:,} planned configurations, wall {wall:.0f} s, task {task:.0f} s; "
                     f"harness {overhead * 1e3:.1f} ms per planned configuration")
        lines.append("  projected task s: " + ", ".join(f"{b} {s:,.0f}" for b, s in sorted(per_b.items(), key=lambda x: -x[1])))
        lines.append(f"  projected sweep: {total:,.0f} s ({total / 3600:.2f} h)"
                     + (f"; no sample configuration ran on {', '.join(missing)} (counted as 0)" if missing else ""))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.studies.sweep_projection", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("sample", help="print a sample's case ids, comma-separated")
    s.add_argument("--every", type=int, default=8)
    s.add_argument("--offset", type=int, default=0)
    j = sub.add_parser("project", help="project the sweep's time from sample runs")
    j.add_argument("run_dirs", nargs="+", type=Path)
    a = p.parse_args(argv)
    if a.cmd == "sample":
        print(",".join(sample_ids(a.every, a.offset)))
        return 0
    counts, planned = sweep_counts()
    print(project(a.run_dirs, counts, planned))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
