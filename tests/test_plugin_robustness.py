"""An untrusted plug-in backend against the harness (a probe's findings, scratch/s71/plugin/REPORT.md):

* a backend's ``os._exit(0)`` inside a configuration is a crash like any other exit, not the
  run's success (bench/run/supervise.py; the whole run: tests/test_crash_isolation.py);
* a configuration killed as hung takes the processes its backend started with it, and SIGINT and
  SIGTERM given to the supervisor still stop the run (its child leads a session of its own);
* ``--timeout`` bounds the conversion of the returned arrays (``__array__``, lazy device arrays);
* ``bench backends`` lists every backend, a broken plug-in's line naming its error, and exits 1;
* a backend is named by its ``id`` however it was loaded (entry point, spec, built-in without
  its device), and two names of one backend clash;
* a result's outputs are checked on their whole shape; a plug-in's ``id`` must be a backend id;
* a run refused at its arguments leaves no ``--out`` directory behind.

The supervisor's tests run a small script as its child (``supervise._command``) instead of
``python -m bench``: the same supervisor, without the seconds a real run takes."""

from __future__ import annotations

import os
import signal
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from bench.run import supervise
from bench.run.contract import OUTPUT_SHAPES, BackendFault, check_result
from impls import METHODS, Prepared, RayResult, Status, registry
from tests.conftest import HANG_GUARD_S, bench_cli
from tests.plugin_backend import PluginBackend

#: a hang guard for waiting on a process that was sent SIGKILL or SIGINT (it is gone at once)
GONE_GUARD_S = 60.0


# --- the supervisor ------------------------------------------------------------------------------

#: the fake child's common part: claims the run directory ``FAKE_OUT`` as ``bench run`` does
#: (bench.run.supervise.note_out) and records its arguments, one line per start
_PROLOGUE = """
import json, os, subprocess, sys, time
from pathlib import Path
out = Path(os.environ["FAKE_OUT"])
out.mkdir(parents=True, exist_ok=True)
Path(os.environ["ISOBENCH_OUT_NOTE"]).write_text(str(out))
with open(out / "calls.txt", "a") as f:
    f.write(" ".join(sys.argv[1:]) + "\\n")
note = out / "inflight.json"
def write_note(pid, **extra):
    note.write_text(json.dumps({"key": ["k"], "what": "the planted configuration", "pid": pid, **extra}))
if "--resume" in sys.argv:  # the resumed runner takes the note over (bench.run.runner.crashed_rows)
    note.unlink(missing_ok=True)
    sys.exit(0)
"""


def _fake_child(monkeypatch, tmp_path, body: str) -> Path:
    """Make ``supervise`` run ``body`` (after :data:`_PROLOGUE`) as its child; returns the run
    directory the child claims."""
    out = tmp_path / "run"
    script = _PROLOGUE + textwrap.dedent(body)
    monkeypatch.setattr(supervise, "_command", lambda args: [sys.executable, "-c", script, *args])
    monkeypatch.setenv("FAKE_OUT", str(out))
    monkeypatch.delenv(supervise.HUNG_AFTER_ENV, raising=False)
    return out


def _calls(out: Path) -> list[str]:
    return (out / "calls.txt").read_text().splitlines()


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie, dead but not yet reaped by its new parent, does not)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    except OSError:  # no /proc: ask the kernel
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        return True
    return state not in ("Z", "X")


def _gone(pid: int) -> bool:
    """Whether ``pid`` is gone, waiting for it up to :data:`GONE_GUARD_S` (a hang guard: a process
    sent SIGKILL goes at once); one still alive then is killed here, not left behind."""
    deadline = time.monotonic() + GONE_GUARD_S
    while _alive(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    if _alive(pid):
        os.kill(pid, signal.SIGKILL)
        return False
    return True


def test_a_child_that_exits_0_inside_a_configuration_is_resumed_past_it(monkeypatch, tmp_path, capfd):
    """Before: exit status 0 ended the supervision whatever the note said, so a backend's
    ``os._exit(0)`` ended the run with status 0, no results, no report and no word.  Now the note
    the child left (its own pid) makes it a crash: said on stderr, resumed with --resume --out."""
    out = _fake_child(monkeypatch, tmp_path, """
        write_note(os.getpid(), started=time.time(), limit_s=0.0)
        os._exit(0)
    """)
    assert supervise.supervise(["run", "--no-claims"]) == 0
    calls = _calls(out)
    assert len(calls) == 2 and calls[0] == "run --no-claims", calls
    assert calls[1] == f"run --no-claims --resume --out {out}"
    err = capfd.readouterr().err
    assert "died (exit status 0) while running the planted configuration" in err, err


def test_a_successful_run_and_a_note_it_did_not_write_restart_nothing(monkeypatch, tmp_path):
    """A run that ends 0 with no note is done (the runner removes its note on every Python path
    out); a note another process left (a pid not the child's: a session killed earlier, whose
    note this child never got as far as taking over, e.g. a resume refused at its arguments)
    does not make the child's exit a crash, else each restart would be refused again."""
    out = _fake_child(monkeypatch, tmp_path, "sys.exit(0)")
    assert supervise.supervise(["run"]) == 0 and len(_calls(out)) == 1
    out2 = _fake_child(monkeypatch, tmp_path / "b", """
        write_note(1, started=time.time(), limit_s=0.0)  # pid 1: not this process
        sys.exit(2)
    """)
    assert supervise.supervise(["run"]) == 2
    assert len(_calls(out2)) == 1, _calls(out2)


def test_a_hung_configuration_is_killed_with_the_processes_its_backend_started(monkeypatch, tmp_path, capfd):
    """Before: the watchdog sent SIGKILL to the child alone, and a helper its backend had started
    (a compile server, a worker) outlived the run.  Now the child leads a session of its own and
    the watchdog kills its process group.  The note says the configuration started at the epoch
    under a limit of 1 s, so it is overdue at the watchdog's first look whatever the machine's
    speed."""
    out = _fake_child(monkeypatch, tmp_path, """
        helper = subprocess.Popen(["sleep", "600"])
        (out / "helper.pid").write_text(str(helper.pid))
        write_note(os.getpid(), started=0.0, limit_s=1.0)
        time.sleep(600)
    """)
    try:
        assert supervise.supervise(["run"]) == 0  # killed, then resumed (the fake resume ends at once)
        assert len(_calls(out)) == 2
        assert "is stuck in the planted configuration" in capfd.readouterr().err
        helper = int((out / "helper.pid").read_text())
        assert _gone(helper), "the backend's helper process outlived its configuration's kill"
    finally:
        if (out / "helper.pid").exists() and _alive(int((out / "helper.pid").read_text())):
            os.kill(int((out / "helper.pid").read_text()), signal.SIGKILL)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_sigint_and_sigterm_to_the_supervisor_stop_the_child_and_its_processes(monkeypatch, tmp_path, signum):
    """The child leads a session of its own (so that a hang kills its group), which takes it out
    of the terminal's foreground group: Ctrl-C reaches the supervisor only.  The supervisor passes
    SIGINT and SIGTERM on to the child's process group (before: SIGINT was ignored by the
    supervisor, SIGTERM passed to the child alone), and the run ends as stopped (128 + signal),
    not restarted.  (The test process takes the signal's interactive disposition first: started
    as a background job of a non-interactive shell, it ignores SIGINT, and so does every process
    it starts; the supervisor then leaves SIGINT ignored, as the next test checks.)"""
    interactive = signal.default_int_handler if signum == signal.SIGINT else signal.SIG_DFL
    launched = signal.signal(signum, interactive)
    out = _fake_child(monkeypatch, tmp_path, """
        helper = subprocess.Popen(["sleep", "600"])
        (out / "helper.pid").write_text(str(helper.pid))
        (out / "ready").write_text("")
        time.sleep(120)  # (only an unforwarded signal lets it run this long)
    """)
    before = signal.getsignal(signum)

    def stop():
        deadline = time.monotonic() + HANG_GUARD_S
        while time.monotonic() < deadline and not ((out / "ready").exists() and signal.getsignal(signum) != before):
            time.sleep(0.02)
        os.kill(os.getpid(), signum)  # to this process: the supervisor

    stopper = threading.Thread(target=stop, daemon=True)
    stopper.start()
    try:
        code = supervise.supervise(["run"])
        stopper.join()
        assert signal.getsignal(signum) == before
        assert code == 128 + signum and len(_calls(out)) == 1
        assert _gone(int((out / "helper.pid").read_text())), "the child's process group did not get the signal"
    finally:
        signal.signal(signum, launched)
        if (out / "helper.pid").exists() and _alive(int((out / "helper.pid").read_text())):
            os.kill(int((out / "helper.pid").read_text()), signal.SIGKILL)


def test_a_supervisor_started_ignoring_sigint_leaves_it_ignored(monkeypatch, tmp_path):
    """Started ignoring SIGINT (a background job of a non-interactive shell, nohup), the supervisor
    installs no handler for it: the child inherits the ignored SIGINT, and the run goes on to its end
    (here the fake child's, exit 0) instead of the supervisor forwarding a signal the run ignores."""
    out = _fake_child(monkeypatch, tmp_path, """
        (out / "ready").write_text("")
        time.sleep(1.0)
    """)
    launched = signal.signal(signal.SIGINT, signal.SIG_IGN)
    seen = []
    try:
        def stop():
            deadline = time.monotonic() + HANG_GUARD_S
            while time.monotonic() < deadline and not (out / "ready").exists():
                time.sleep(0.02)
            seen.append(signal.getsignal(signal.SIGINT))  # while the child runs
            os.kill(os.getpid(), signal.SIGINT)

        stopper = threading.Thread(target=stop, daemon=True)
        stopper.start()
        assert supervise.supervise(["run"]) == 0
        stopper.join()
        assert seen == [signal.SIG_IGN], seen
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN and len(_calls(out)) == 1
    finally:
        signal.signal(signal.SIGINT, launched)


# --- the time limit bounds the conversion of the result ---------------------------------------------

class _SlowArray:
    """An array-like whose conversion (``__array__``, as a lazy device array's queued work) takes
    :attr:`SLEEP_S` seconds."""

    SLEEP_S = 120.0

    def __init__(self, a):
        self.a = a

    def __array__(self, dtype=None, copy=None):
        time.sleep(self.SLEEP_S)
        return np.asarray(self.a, dtype=dtype)


class SlowConversionBackend(PluginBackend):
    """tests/plugin_backend.py's numpy wrapper whose result's ``t`` converts slowly."""

    def __init__(self, device: str = "cpu"):
        super().__init__(device)
        self.id = "slowconv"

    def prepare(self, method, scene, origins, directions, **kwargs):
        p = super().prepare(method, scene, origins, directions, **kwargs)

        def result(out):
            r = p.result(out)
            return RayResult(t=_SlowArray(r.t), status=r.status, iterations=r.iterations, evals=r.evals,
                             outputs=r.outputs)

        return Prepared(run=p.run, result=result)


def test_the_timeout_bounds_the_conversion_of_the_returned_arrays(tmp_path):
    """Before: ``check_result`` converted the arrays after the time limit's block, so a conversion
    of 20 s under ``--timeout 5`` was an ok row (and untimed: the backend was picked as fastest).
    Now the conversion runs inside the limit: a Timeout row.  (Had the conversion not been
    interrupted, the row would be ok after SLEEP_S seconds.)"""
    from bench.run import runner
    from bench.run.suites import Suite
    from bench.run.timing import TimingPolicy

    suite = Suite(name="t", case_pattern="sphere.camera.64x64", dtypes=("float64",),
                  sweeps={"hybrid_secant": [{}]}, methods=("hybrid_secant",))
    policy = TimingPolicy(min_repeats=1, min_time_s=0.0, min_sample_s=0.0, warmup=0, timeout_s=2.0,
                          accuracy_only=True)
    df = runner.run(suite, {"slowconv": SlowConversionBackend()}, tmp_path, policy=policy)
    assert set(df["outcome"]) == {"failed"}, df[["outcome", "reason"]]
    assert df["reason"].str.startswith("Timeout: ran past the time limit of 2 s").all(), df["reason"].iloc[0]


# --- bench backends --------------------------------------------------------------------------------

class MethodsRaise(PluginBackend):
    def __init__(self, device: str = "cpu"):
        super().__init__(device)
        self.id = "methods-raise"

    def methods(self):
        raise RuntimeError("planted: methods() is broken")


class CapabilitiesRaise(PluginBackend):
    def __init__(self, device: str = "cpu"):
        super().__init__(device)
        self.id = "caps-raise"

    @property
    def capabilities(self):
        raise RuntimeError("planted: capabilities is broken")

    @capabilities.setter
    def capabilities(self, value):
        pass


@pytest.mark.parametrize("cls, words", [("MethodsRaise", ["methods-raise", "methods() raised RuntimeError",
                                                          "planted: methods() is broken"]),
                                        ("CapabilitiesRaise", ["caps-raise", "capabilities raised RuntimeError",
                                                               "planted: capabilities is broken"])])
def test_bench_backends_lists_every_backend_past_a_broken_plugin(monkeypatch, capsys, cls, words):
    """Before: a traceback at the broken plug-in, and the backends after it never listed.  Now its
    line names it and the exception, every other backend is listed, and the exit status is 1."""
    from bench.commands import main

    spec = f"tests.test_plugin_robustness:{cls}"
    monkeypatch.setattr(registry, "default_ids", lambda: ["numpy", spec, "tests.plugin_backend:PluginBackend"])
    code = main(["backends"])
    got = capsys.readouterr()
    lines = got.out.splitlines()
    assert code == 1
    bad = [ln for ln in lines if ln.startswith(words[0])]
    assert len(bad) == 1 and all(w in bad[0] for w in words), got.out
    assert any(ln.startswith("numpy ") for ln in lines) and any(ln.startswith("npwrap ") for ln in lines), got.out
    assert "error:" in got.err and words[0] in got.err


def test_bench_backends_exits_0_when_every_backend_answers(monkeypatch, capsys):
    from bench.commands import main

    monkeypatch.setattr(registry, "default_ids", lambda: ["numpy", "tests.plugin_backend:PluginBackend",
                                                          "tests.no_such_module:X"])
    assert main(["backends"]) == 0  # an unavailable one is listed with the reason, not an error
    out = capsys.readouterr().out
    assert "npwrap " in out and "tests.no_such_module:X unavailable" in out


# --- a backend is named by its id ------------------------------------------------------------------

def _entry_point(tmp_path, monkeypatch, name: str, target: str) -> None:
    """An installed distribution declaring ``[isobench.backends] name = target`` (a dist-info folder
    on sys.path is what pip install writes)."""
    dist = tmp_path / f"{name}_plugin-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}-plugin\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(f"[{registry.ENTRY_POINT_GROUP}]\n{name} = {target}\n")
    monkeypatch.syspath_prepend(str(tmp_path))


def test_an_entry_point_plugin_is_named_by_its_id_and_clashes_with_itself(tmp_path, monkeypatch):
    """Before: an entry point's rows were named by the entry point's name (``myep``), the same
    class given as a spec by its id (``npwrap``): one plug-in, two names, and ``bench compare``
    between the two saw missing and new rows.  Now both are ``npwrap``, and naming it both ways is
    refused as naming one backend twice; a built-in given without its device is its id too."""
    from bench.commands._common import resolve_backends

    _entry_point(tmp_path, monkeypatch, "myep", "tests.plugin_backend:PluginBackend")
    specs: dict = {}
    backends, msg = resolve_backends(["myep", "numpy"], 1, specs=specs)
    assert msg == "" and list(backends) == ["npwrap", "numpy"]
    assert specs == {"npwrap": "myep", "numpy": "numpy"}  # other processes resolve it by the entry point
    backends, msg = resolve_backends(["myep", "tests.plugin_backend:PluginBackend"], 1)
    assert backends is None and msg == ("--backend: 'tests.plugin_backend:PluginBackend' and 'myep' both name the "
                                        "backend 'npwrap'; give one of them")
    backends, msg = resolve_backends(["numpy", "numpy:cpu"], 1)
    assert backends is None and "both name the backend 'numpy'" in msg


# --- the result's outputs, whole shape ---------------------------------------------------------------

def _result(n: int, **outputs) -> RayResult:
    return RayResult(t=np.ones(n), status=np.zeros(n, np.int64), iterations=np.zeros(n, np.int64),
                     evals=np.ones(n, np.int64), outputs=outputs)


class _Scene:
    def param_vector(self):
        return np.zeros(4)


def test_every_catalog_output_has_a_shape():
    """A method's new output needs its shape in the contract's table, or only its leading
    dimension is checked."""
    declared = {o for spec in METHODS.values() for o in spec.outputs}
    assert declared <= set(OUTPUT_SHAPES), sorted(declared - set(OUTPUT_SHAPES))


@pytest.mark.parametrize("name, got, want", [
    ("normal", (8, 1), "(8, 3)"), ("normal", (8,), "(8, 3)"), ("color", (8, 4), "(8, 3)"),
    ("curvature_laplacian", (8, 1), "(8,)"), ("dt_dtheta", (8, 3), "(8, 4)"), ("dt_dtheta", (8,), "(8, 4)"),
])
def test_an_output_of_the_wrong_shape_is_a_fault_naming_it(name, got, want):
    """Before: only the leading dimension was checked; a normal of shape (n, 1) passed and failed
    later in the metrics with numpy's "incompatible dimensions for cross product", which named
    neither the output nor the backend."""
    with pytest.raises(BackendFault) as exc:
        check_result(_result(8, **{name: np.zeros(got)}), 8, (name,), scene=_Scene(), who="liar")
    text = str(exc.value)
    assert f"output {name} of liar" in text and str(got) in text and f"expected {want}" in text, text


def test_outputs_of_the_right_shape_pass():
    res = check_result(_result(8, normal=np.ones((8, 3)), dt_dtheta=np.ones((8, 4)), opacity=np.ones(8)), 8,
                       ("normal", "dt_dtheta", "opacity"), scene=_Scene())
    assert res.outputs["normal"].shape == (8, 3)
    # without a scene, dt/dθ may have any number of columns (one per parameter)
    check_result(_result(8, dt_dtheta=np.ones((8, 2))), 8, ("dt_dtheta",))


@pytest.mark.parametrize("name, value, words", [
    ("evals", 1e300, r"whole counts in \[0, 2147483647\] \(int32\); got min 1e\+300"), ("iterations", 1e20, "whole counts"),
    ("evals", 0.001, "not whole numbers"), ("evals", 2**31, "whole counts"),
])
def test_counts_beyond_int32_or_fractional_are_a_fault(name, value, words):
    """Before: any finite count ≥ 0 passed.  1e300 evaluations then overflowed the results file's
    int64 column, which lost every backend's rows and stopped --resume at the same place, and
    0.001 evaluations a ray won "which to pick" for the backend that claimed it (the 2026-11-30
    plug-in probe)."""
    res = _result(8)
    setattr(res, name, np.full(8, value))
    with pytest.raises(BackendFault, match=f"result {name} must be {words}" if "whole counts" in words
                       else f"result {name} .*{words}"):
        check_result(res, 8, ())


def test_a_float32_answer_in_a_float64_configuration_is_a_fault():
    res = _result(8)
    res.t = np.asarray(res.t, np.float32)
    with pytest.raises(BackendFault, match="result t has dtype float32 in a float64 configuration"):
        check_result(res, 8, (), dtype="float64")
    check_result(res, 8, (), dtype="float32")
    with pytest.raises(BackendFault, match="output normal has dtype float32"):
        check_result(_result(8, normal=np.ones((8, 3), np.float32)), 8, ("normal",), dtype="float64")


def test_a_root_finders_depth_outside_its_interval_or_a_finite_miss_is_a_fault():
    """A CONVERGED depth before t_min (a plug-in's negated depths) or past t_max, and a MISS with
    a finite t, break the status table; before, they were scored as depth errors or false misses."""
    res = _result(8)
    res.status = np.zeros(8, np.int32)
    res.t = np.full(8, 2.0)
    check_result(res, 8, (), t_range=(0.0, 6.0))
    res.t[3] = -2.0
    with pytest.raises(BackendFault, match=r"1 rays CONVERGED at a depth outside \[t_min, t_max\] = \[0, 6\] \(ray 3"):
        check_result(res, 8, (), t_range=(0.0, 6.0))
    res.t[3] = 6.0 + 4e-15  # within rounding of t_max
    check_result(res, 8, (), t_range=(0.0, 6.0))
    res.status[5] = int(Status.MISS)
    with pytest.raises(BackendFault, match=r"1 rays are MISS with t ≠ inf \(ray 5"):
        check_result(res, 8, (), t_range=(0.0, 6.0))


# --- a plug-in's id ----------------------------------------------------------------------------------

def _named(backend_id):
    """A subclass of the test plug-in whose instances carry ``backend_id`` as their id."""
    class Named(PluginBackend):
        def __init__(self, device: str = "cpu"):
            super().__init__(device)
            self.id = backend_id

    return Named


BadId = _named("x<img src=x onerror=alert(1)>/y|z")
NoStrId = _named(42)


@pytest.mark.parametrize("cls, words", [("BadId", ["\\u003c", "\\u007c", "letters, digits and _.:+-"]),
                                        ("NoStrId", ["not a string but int"])])
def test_a_plugin_whose_id_is_no_backend_id_is_unavailable_naming_it(cls, words):
    """Before: any string was an id, written raw into report.md (a ``|`` split its table cells)
    and HTML.  Now a plug-in whose ``id`` is not letters, digits and ``_.:+-`` is unavailable (a
    skipped backend, as one that fails to load), the reason naming ``id`` and the fix, its
    characters escaped."""
    from bench.commands._common import resolve_backends

    spec = f"tests.test_plugin_robustness:{cls}"
    b = registry.resolve(spec)
    assert isinstance(b, registry.Unavailable) and not b.unknown
    assert "its id" in b.reason and "set the backend's `id` attribute" in b.reason
    assert all(w in b.reason for w in words), b.reason
    assert "<" not in b.reason and "|" not in b.reason
    backends, msg = resolve_backends([spec, "numpy"], 1)  # a run skips it, named by its spec
    assert msg == "" and list(backends) == [spec, "numpy"]


AsTorch, AsNumba = _named("torch:cpu"), _named("numba")


@pytest.mark.parametrize("cls, lib", [("AsTorch", "torch"), ("AsNumba", "numba")])
def test_a_plugin_may_not_take_another_backends_id(cls, lib):
    """Before: a plug-in called ``torch:cpu`` in a run without torch had its rows labelled, compared
    and baselined as torch's (the 2026-11-30 plug-in probe).  A built-in's library or another
    entry point's name is refused; the entry point's own target named as a spec is that backend."""
    b = registry.resolve(f"tests.test_plugin_robustness:{cls}")
    assert isinstance(b, registry.Unavailable)
    assert f"names the backend {lib!r}" in b.reason, b.reason
    numba = registry.resolve("impls.numba.backend:NumbaBackend")
    assert getattr(numba, "id", None) == "numba" or isinstance(numba, registry.Unavailable)


def test_the_builtin_and_test_backend_ids_are_backend_ids():
    for bid in ("numpy", "torch:cpu", "torch:cuda", "torch:cuda:1", "jax:cpu", "jax:gpu", "numba", "embree",
                "open3d", "warp:cpu", "warp:cuda", "mitsuba:llvm", "mitsuba:cuda", "npwrap", "crashy", "fake",
                "BadStatusBackend", "KillOnce", "Slow", "my_lib.v2+fast-x"):
        assert registry.id_problem(bid) is None, bid
    for spec in ("tests.plugin_backend:PluginBackend", "tests.crash_backend:CrashBackend",
                 "tests.test_bench_fakes:BadStatusBackend", "tests.cluster_backends:KillOnce"):
        assert not isinstance(registry.resolve(spec), registry.Unavailable), spec


# --- a refused run leaves no --out behind ------------------------------------------------------------

@pytest.mark.parametrize("how", ["method", "clash"])
def test_a_run_refused_at_its_arguments_leaves_no_new_out_directory(tmp_path, how):
    """Before: ``--method volume_made_up`` (exit 2) left the new ``--out`` with a lock file in it.
    Now the method names are checked before the directory is claimed, and a refusal after the
    claim (two names of one backend: known once the backends are loaded) gives back the directory
    it created while nothing but its lock is in it."""
    out = tmp_path / "new" / "run"
    args = {"method": ["--backend", "numpy", "--method", "volume_made_up"],
            "clash": ["--backend", "tests.plugin_backend:PluginBackend,tests.plugin_backend:PluginBackend"]}[how]
    p = bench_cli("run", "--case", "sphere.camera.64x64", "--no-claims", "--no-stability", "--out", out, *args)
    assert p.returncode == 2, p.stdout[-2000:] + p.stderr[-2000:]
    assert ("unknown method(s) ['volume_made_up']" if how == "method" else "both name the backend 'npwrap'") in p.stderr
    assert not (tmp_path / "new").exists(), sorted(map(str, tmp_path.rglob("*")))


def test_a_discarded_claim_keeps_what_it_did_not_create_or_was_written(tmp_path):
    from bench.run.rundir import LOCK_FILE, _same_file, claim_out

    lock = claim_out(tmp_path / "a" / "b")
    assert lock.created == [(tmp_path / "a" / "b").absolute(), (tmp_path / "a").absolute()]
    lock.discard()
    assert not (tmp_path / "a").exists()
    (tmp_path / "empty").mkdir()
    claim_out(tmp_path / "empty").discard()  # there before: kept
    assert (tmp_path / "empty").is_dir()
    lock = claim_out(tmp_path / "written")
    (tmp_path / "written" / "environment.json").write_text("{}")
    lock.discard()  # something was written: kept as it is
    assert (tmp_path / "written" / "environment.json").exists() and (tmp_path / "written" / LOCK_FILE).exists()
    # a process that opened the lock file before a holder gave the directory up finds it removed
    fd = os.open(tmp_path / "written" / LOCK_FILE, os.O_RDWR)
    try:
        assert _same_file(fd, tmp_path / "written" / LOCK_FILE)
        (tmp_path / "written" / LOCK_FILE).unlink()
        assert not _same_file(fd, tmp_path / "written" / LOCK_FILE)
    finally:
        os.close(fd)
