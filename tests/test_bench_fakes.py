"""A fake backend and fake methods of every family, for testing bench's generic machinery.

The fake methods compute the exact answer from the reference and add a *planted* error of known
size, so a test can check that bench measures exactly that error.  ``behaviour`` knobs make a
method raise, return a wrong shape, a silent NaN, or hang (to test failure rows and timeouts).
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from impls.methods import Knob, MethodSpec
from impls.protocol import Capabilities, Prepared, RayResult, Status

PLANTED = 1e-6  # the error the fake methods add


def _rotate_small(n: np.ndarray, angle: float) -> np.ndarray:
    """Rotate unit vectors n by ``angle`` about an axis perpendicular to each."""
    a = np.cross(n, np.array([0.3, 0.5, 0.8]))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    return n * math.cos(angle) + np.cross(a, n) * math.sin(angle)


def fake_root(scene, o, d, t_min, t_max, t_hit, tol, max_steps, behaviour=0):
    t = scene.first_hit(o, d, t_min)
    t = np.where(t <= t_max, t, np.inf)
    hit = np.isfinite(t)
    out_t = np.where(hit, t + PLANTED * (1 + tol), np.inf)  # planted error, slightly tol-dependent
    status = np.where(hit, Status.CONVERGED, Status.MISS).astype(np.int32)
    if behaviour == 1:
        raise RuntimeError("planted failure")
    if behaviour == 2:
        out_t = out_t[:-1]
    if behaviour == 3:
        out_t = np.where(hit, np.nan, out_t)
    if behaviour == 4:
        deadline = time.perf_counter() + 30
        while time.perf_counter() < deadline:  # a hang in Python code
            pass
    n = o.shape[0]
    return {"t": out_t, "status": status, "iterations": np.full(n, max_steps, np.int32),
            "evals": np.full(n, max_steps + 1, np.int32)}


def fake_normal(scene, o, d, t_min, t_max, t_hit, n_fd, behaviour=0):
    hit = np.isfinite(t_hit)
    x = o + np.where(hit, t_hit, 0)[:, None] * d
    v = x - np.asarray(scene.center)  # the sphere's normal, computed here, not by the reference
    nrm = _rotate_small(v / np.linalg.norm(v, axis=1, keepdims=True), PLANTED)
    lap = np.full(o.shape[0], 2.0 / scene.radius) + PLANTED
    status = np.where(hit, Status.CONVERGED, Status.MISS).astype(np.int32)
    nrm[~hit] = np.nan
    lap[~hit] = np.nan
    n = o.shape[0]
    return {"t": t_hit, "status": status, "iterations": np.ones(n, np.int32), "evals": np.full(n, n_fd, np.int32),
            "normal": nrm, "curvature_laplacian": lap}


def fake_dt(scene, o, d, t_min, t_max, t_hit, n_fd, behaviour=0):
    hit = np.isfinite(t_hit)
    g = np.full((o.shape[0], scene.param_vector().size), np.nan)
    g[hit] = scene.hit_param_grad(o[hit], d[hit], t_hit[hit]) + PLANTED
    status = np.where(hit, Status.CONVERGED, Status.MISS).astype(np.int32)
    # a grazing-ray guard: decline the ray with the smallest |n·d|
    nd = np.full(o.shape[0], np.inf)
    nd[hit] = np.abs(np.einsum("ij,ij->i", scene.normal_exact(o[hit] + t_hit[hit, None] * d[hit]), d[hit]))
    worst = int(np.argmin(nd))
    status[worst] = Status.ILL_CONDITIONED
    g[worst] = np.nan
    n = o.shape[0]
    return {"t": t_hit, "status": status, "iterations": np.ones(n, np.int32), "evals": np.ones(n, np.int32),
            "dt_dtheta": g}


def fake_render(scene, o, d, t_min, t_max, t_hit, n_samples, behaviour=0):
    n = o.shape[0]
    return {"t": np.zeros(n), "status": np.zeros(n, np.int32), "iterations": np.ones(n, np.int32),
            "evals": np.full(n, n_samples, np.int32), "color": np.zeros((n, 3))}


FAKE_METHODS = {
    "fake_root": MethodSpec("fake_root", "root", (Knob("tol", 1e-6, float, 0.0, "tolerance", role="tolerance"),
                                                  Knob("max_steps", 8, int, 1, "budget", role="budget"),
                                                  Knob("behaviour", 0, int, 0, "0 ok, 1 raise, 2 shape, 3 NaN, 4 hang", role="setting")),
                            ("lipschitz",), "exact hit + planted error"),
    "fake_normal": MethodSpec("fake_normal", "gradient", (Knob("n_fd", 4, int, 1, "evals", role="budget"),),
                              (), "exact normal rotated by a planted angle", needs_t_hit=True,
                              outputs=("normal", "curvature_laplacian")),
    "fake_dt": MethodSpec("fake_dt", "param_grad", (Knob("n_fd", 2, int, 1, "evals", role="budget"),),
                          (), "exact dt/dθ + planted error", needs_t_hit=True, outputs=("dt_dtheta",)),
    "fake_render": MethodSpec("fake_render", "render", (Knob("n_samples", 8, int, 1, "samples", role="budget"),),
                              (), "black image", outputs=("color",)),
}
_IMPL = {"fake_root": fake_root, "fake_normal": fake_normal, "fake_dt": fake_dt, "fake_render": fake_render}


class FakeBackend:
    """Implements the :class:`impls.protocol.Backend` protocol with numpy and the fake methods."""

    lib = "fake"
    device = "cpu"
    capabilities = Capabilities(dtypes=("float64",), devices=("cpu",))

    def __init__(self, backend_id: str = "fake", methods=None):
        self.id = backend_id
        self._methods = tuple(_IMPL if methods is None else methods)
        self.calls: list[str] = []

    def methods(self):
        return self._methods

    def prepare(self, method, scene, origins, directions, *, dtype="float64", t_min=0.0, t_max=math.inf,
                t_hit=None, **knobs):
        spec = FAKE_METHODS[method]
        knobs = spec.validate(knobs)
        fn = _IMPL[method]
        o, d = np.asarray(origins, float), np.asarray(directions, float)
        th = None if t_hit is None else np.asarray(t_hit, float)

        def run():
            self.calls.append(method)
            return fn(scene, o, d, t_min, t_max, th, **knobs)

        def result(out):
            out = dict(out)
            return RayResult(t=out.pop("t"), status=out.pop("status"), iterations=out.pop("iterations"),
                             evals=out.pop("evals"), outputs=out)

        return Prepared(run=run, result=result)

    def synchronize(self, out=None):
        pass

    def versions(self):
        return {"fake": "1"}


class FakeColor:
    """ρ(x) = (x + 2)/4 per channel (values in [0, 1] near the unit sphere)."""

    def value(self, x, xp=np):
        return (x + 2.0) / 4.0


def fake_render_exact(scene, color, model, sharpness, o, d, t_min, t_max, *, tol=1e-12):
    """Stand-in for ``reference.rendering.render_exact``: ρ at the exact hit blurred by 1/s."""
    if model == "unisurf":
        raise ValueError("unisurf has no continuous density")
    t = scene.first_hit(o, d, t_min)
    hit = np.isfinite(t) & (t <= t_max)
    out = np.zeros((o.shape[0], 3))
    out[hit] = color.value(o[hit] + t[hit, None] * d[hit]) * (1 - 1 / sharpness)
    return out, np.full(o.shape[0], 1e-11)


def fake_volume(scene, o, d, t_min, t_max, t_hit, n_samples, sharpness, behaviour=0):
    """'Renders' the fake integral plus a planted error."""
    c, _ = fake_render_exact(scene, FakeColor(), "nerf", sharpness, o, d, t_min, t_max)
    n = o.shape[0]
    return {"t": np.zeros(n), "status": np.zeros(n, np.int32), "iterations": np.ones(n, np.int32),
            "evals": np.full(n, n_samples, np.int32), "color": c + PLANTED}


_VOLUME_KNOBS = (Knob("n_samples", 8, int, 1, "samples", role="budget"), Knob("sharpness", 50.0, float, 1e-9, "s", role="setting"))
FAKE_METHODS.update({
    f"volume_{m}_uniform": MethodSpec(f"volume_{m}_uniform", "render", _VOLUME_KNOBS, (), "fake volume", outputs=("color",))
    for m in ("nerf", "unisurf")
})
_IMPL.update({f"volume_{m}_uniform": fake_volume for m in ("nerf", "unisurf")})


# --- faulty plug-ins: user backends that break the protocol in one way each -------------------------------
# (wrapping the numpy backend; each is loadable as ``--backend tests.test_bench_fakes:<Class>``)

import types  # noqa: E402


class _WrapsNumpy:
    """A user backend wrapping numpy, with one fault planted by a subclass."""

    lib = "faulty"
    device = "cpu"

    def __init__(self):
        from impls.numpy.backend import NumpyBackend

        self._inner = NumpyBackend("cpu")
        self.id = type(self).__name__

    @property
    def capabilities(self):
        return self._inner.capabilities

    def methods(self):
        return ("sphere_trace", "hybrid_secant")

    def prepare(self, method, scene, origins, directions, **kw):
        return self._inner.prepare(method, scene, origins, directions, **kw)

    def synchronize(self, out=None):
        return None

    def versions(self):
        return {"faulty": "0.1"}


class BadStatusBackend(_WrapsNumpy):
    """Returns status code 7 (not an ``impls.protocol.Status``) on the first ray."""

    def prepare(self, *a, **kw):
        p = super().prepare(*a, **kw)

        def result(out):
            r = p.result(out)
            r.status = r.status.copy()
            r.status[0] = 7
            return r

        return Prepared(run=p.run, result=result, compile_s=p.compile_s)


class NoCompileSBackend(_WrapsNumpy):
    """``prepare`` returns an object with ``run`` and ``result`` but no ``compile_s``."""

    def prepare(self, *a, **kw):
        p = super().prepare(*a, **kw)
        return types.SimpleNamespace(run=p.run, result=p.result)


class NoStatusCountsBackend(_WrapsNumpy):
    """``result`` returns a plain namespace (no ``status_counts`` method), statuses as int8."""

    def prepare(self, *a, **kw):
        p = super().prepare(*a, **kw)

        def result(out):
            r = p.result(out)
            return types.SimpleNamespace(t=r.t, status=r.status.astype(np.int8), iterations=r.iterations,
                                         evals=r.evals, outputs=r.outputs)

        return Prepared(run=p.run, result=result)


class StatusCountsLiesBackend(_WrapsNumpy):
    """A RayResult whose ``status_counts`` raises: the runner must not call it."""

    def prepare(self, *a, **kw):
        p = super().prepare(*a, **kw)

        class Lying(RayResult):
            def status_counts(self):
                raise RuntimeError("the user's status_counts was called")

        def result(out):
            r = p.result(out)
            return Lying(t=r.t, status=r.status, iterations=r.iterations, evals=r.evals, outputs=r.outputs)

        return Prepared(run=p.run, result=result)


class VersionsRaiseBackend(_WrapsNumpy):
    def versions(self):
        raise RuntimeError("planted: versions() is broken")


class MethodsRaiseBackend(_WrapsNumpy):
    def methods(self):
        raise RuntimeError("planted: methods() is broken")


class CapabilitiesRaiseBackend(_WrapsNumpy):
    @property
    def capabilities(self):
        raise RuntimeError("planted: capabilities is broken")


class WrongResultBackend(_WrapsNumpy):
    """Returns a tuple instead of a RayResult."""

    def prepare(self, *a, **kw):
        p = super().prepare(*a, **kw)
        return Prepared(run=p.run, result=lambda out: (p.result(out).t,))


class MutatingBackend(_WrapsNumpy):
    """Writes into its inputs, as a user's in-place bug would: moves the rays' origins 0.25 along
    their directions and scales a given ``t_hit`` by 1.01, then solves the moved rays."""

    def methods(self):
        return ("sphere_trace", "hybrid_secant", "normal")

    def prepare(self, method, scene, origins, directions, **kw):
        origins += 0.25 * directions
        if kw.get("t_hit") is not None:
            kw["t_hit"] *= 1.01
        return self._inner.prepare(method, scene, origins, directions, **kw)


class SceneMutatingBackend(_WrapsNumpy):
    """Writes into the scene it is given: scales the first weight matrix of an MLP field by 1.5 in
    place (a user's in-place "normalisation" of the network), then solves."""

    def prepare(self, method, scene, origins, directions, **kw):
        w = scene.weights["W1"]
        np.multiply(w, 1.5, out=w)
        return self._inner.prepare(method, scene, origins, directions, **kw)


class GlobalStateBackend(_WrapsNumpy):
    """Changes process-wide library settings in ``prepare``, as a user's library might on import or
    first use: numpy's floating-point errors raise, and torch's default dtype becomes float32."""

    def prepare(self, *a, **kw):
        np.seterr(all="raise")
        try:
            import torch

            torch.set_default_dtype(torch.float32)
        except ImportError:
            pass
        return super().prepare(*a, **kw)


class FloatStatusBackend(_WrapsNumpy):
    """Statuses as float with a fractional value."""

    def prepare(self, *a, **kw):
        p = super().prepare(*a, **kw)

        def result(out):
            r = p.result(out)
            r.status = r.status.astype(np.float64) + 0.5
            return r

        return Prepared(run=p.run, result=result)


class ExitsBackend(_WrapsNumpy):
    """``run`` calls ``sys.exit`` (a user library that exits instead of raising)."""

    def prepare(self, *a, **kw):
        p = super().prepare(*a, **kw)

        def run():
            raise SystemExit(3)

        return Prepared(run=run, result=p.result)


class SceneRebindingBackend(_WrapsNumpy):
    """``prepare`` moves the scene it is given: a sphere's radius 1 → 1.5 (a plug-in that tunes
    the field it was handed instead of its own copy)."""

    def prepare(self, method, scene, origins, directions, **kw):
        object.__setattr__(scene, "radius", 1.5)
        return super().prepare(method, scene, origins, directions, **kw)


class LazyResultBackend(_WrapsNumpy):
    """``run`` does nothing and ``result`` does the work (untimed by the protocol): 20 runs of
    numpy's, well past the floor of ``untimed_work`` (0.05 s) on any machine."""

    def prepare(self, *a, **kw):
        p = super().prepare(*a, **kw)

        def result(_):
            for _ in range(19):
                p.run()
            return p.result(p.run())

        return Prepared(run=lambda: None, result=result)


class KeyboardInterruptBackend(_WrapsNumpy):
    """``run`` raises KeyboardInterrupt itself, with no Ctrl-C behind it."""

    def prepare(self, *a, **kw):
        p = super().prepare(*a, **kw)

        def run():
            raise KeyboardInterrupt("planted")

        return Prepared(run=run, result=p.result)


class OwnBaseException(BaseException):
    pass


class BaseExceptionBackend(_WrapsNumpy):
    """``prepare`` raises a BaseException subclass of the plug-in's own."""

    def prepare(self, *a, **kw):
        raise OwnBaseException("planted")


class CountsLieBackend(_WrapsNumpy):
    """``evals`` of ``EVALS`` per ray: beyond int32 (1e300 overflowed the results file) or a
    fraction (0.001 a ray won "which to pick")."""

    EVALS = 1e300

    def prepare(self, *a, **kw):
        p = super().prepare(*a, **kw)

        def result(out):
            r = p.result(out)
            return dataclasses.replace(r, evals=np.full(r.evals.shape, self.EVALS))

        return Prepared(run=p.run, result=result)


class FractionalEvalsBackend(CountsLieBackend):
    EVALS = 0.001


class SleepyBackend(_WrapsNumpy):
    """Every call sleeps ``SLEEP_S`` seconds (a hang in a user backend), swallowing Exceptions."""

    SLEEP_S = 30.0

    def prepare(self, *a, **kw):
        p = super().prepare(*a, **kw)

        def run():
            try:
                time.sleep(self.SLEEP_S)
            except Exception:  # a careless user backend: must not swallow the time limit
                pass
            return p.run()

        return Prepared(run=run, result=p.result)


class BrokenFactoryBackend(_WrapsNumpy):
    """Exists, but cannot be made (its library is broken): unavailable, not unknown."""

    def __init__(self):
        raise ImportError("planted: the user's library failed to load")
