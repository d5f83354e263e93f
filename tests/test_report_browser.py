"""The report as a person sees it: rendered by a headless browser, its first screen holds the run
summary and "Which to pick".

The report itself has no scripts; the test renders a copy with one added script that records,
after layout, which headings start inside the first 1400×1000 screen, and reads the DOM back
(``chromium --dump-dom``).  ``.ci/run`` installs Chromium (Debian's package) when it is missing;
elsewhere the test is skipped with that reason.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess

import pandas as pd
import pytest

from bench.report import build as report
from tests.conftest import HANG_GUARD_S

BROWSER = next((shutil.which(b) for b in ("chromium", "chromium-browser", "google-chrome") if shutil.which(b)), None)

PROBE = """<script>
window.addEventListener('load', () => {
  const seen = [...document.querySelectorAll('h1,h2,p,table')]
    .filter(el => el.getBoundingClientRect().top < window.innerHeight)
    .map(el => el.tagName + ':' + el.innerText.slice(0, 200));
  const out = document.createElement('pre');
  out.id = 'probe';
  out.textContent = JSON.stringify(seen);
  document.body.appendChild(out);
});
</script>"""


def _rows():
    rows = []
    for case in ("sphere.camera.64x64", "torus.camera.32x32", "csg.union.camera.32x32", "mlp.camera.32x32"):
        for backend, ratio in (("numpy", 9.0), ("jax:cpu", 4.0)):
            for method, err in (("hybrid_secant", 1e-13), ("sphere_trace", 1e-9)):
                rows.append({"case_id": case, "case_version": "v", "backend": backend, "device": "cpu",
                             "dtype": "float64", "method": method, "family": "root", "knob": "", "knobs_json": "{}", "quantity": "depth",
                             "outcome": "ok", "reason": "", "error_max": err, "time_median_s": ratio * 1e-3,
                             "time_iqr_s": 1e-5, "time_ratio_cf": ratio, "compile_s": 0.0, "evals_per_ray": 4.0,
                             "n_false_hit": 0, "n_false_miss": 0, "status_counts": json.dumps({"CONVERGED": 10})})
    return pd.DataFrame(rows)


@pytest.mark.slow  # starts a headless browser
@pytest.mark.skipif(BROWSER is None, reason="no headless browser (apt-get install chromium; .ci/run does)")
def test_first_screen_holds_the_summary_and_which_to_pick(tmp_path):
    env = {"run_id": "r-browser", "suite": "quick", "commit": "abc123", "cpu": "test cpu", "complete": "true"}
    report.build(_rows(), env, tmp_path, scoreboard=["numpy: 11/12 families survived"])
    page = (tmp_path / "report.html").read_text()
    probe = tmp_path / "probe.html"
    probe.write_text(page.replace("</body>", PROBE + "</body>"))
    out = subprocess.run([BROWSER, "--headless", "--no-sandbox", "--disable-gpu", "--window-size=1400,1000",
                          "--virtual-time-budget=5000", "--dump-dom", probe.as_uri()],
                         capture_output=True, text=True, timeout=HANG_GUARD_S)
    m = re.search(r"<pre id=\"probe\">(.*?)</pre>", out.stdout, re.S)
    assert m, f"the browser did not render the page: {out.stderr[-2000:]}"
    seen = json.loads(m.group(1).replace("&quot;", '"').replace("&amp;", "&").replace("&lt;", "<")
                      .replace("&gt;", ">"))
    text = "\n".join(seen)
    assert "r-browser" in text and "configurations ran" in text  # the run and its counts
    assert "H2:Which to pick" in seen
    assert "hybrid_secant · jax:cpu · float64" in text  # the pick itself, not only its heading
    # the detail tables come after the first screen's answers
    assert "H2:Best accuracy per backend" not in seen or (
        seen.index("H2:Which to pick") < seen.index("H2:Best accuracy per backend"))
