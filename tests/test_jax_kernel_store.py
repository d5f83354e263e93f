"""The jax kernel store (:mod:`impls.jax.executables`): a kernel found by what it computes, with
no trace, gives exactly what the traced kernel gives; anything the key cannot see (a user's
class or function, a host call) is never stored; a damaged entry is a miss.

The scenes here carry a parameter drawn afresh per session (:data:`FRESH`): the store keeps only
kernels XLA compiled in the process, and a program jax's persistent cache (the user's cache
directory, shared with earlier sessions) already holds would be loaded from there instead."""

from __future__ import annotations

import dataclasses
import os
import random

import numpy as np
import pytest

from impls.jax import executables
from reference import Sphere, Torus
from tests.conftest import resolve_or_skip


#: a radius offset of this session: programs no earlier session compiled.  A whole multiple of
#: 2**-22, so that it survives rounding to float32 (whose spacing is 2**-25 at 0.3 and 2**-23 at
#: 1.0): an offset below half a float32 spacing vanished there, and a float32 program compiled in
#: an earlier session (a cache directory outlives sessions) was found in jax's persistent cache
#: and, rightly, not stored.  2**16 offsets: two sessions draw the same one with probability 2**-16.
FRESH = random.Random().randrange(1, 2**16) * 2.0**-22


def _rays(n=48):
    rng = np.random.default_rng(1)
    o = np.tile([0.0, 0.0, -3.0], (n, 1))
    d = np.column_stack([rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), np.ones(n)])
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def _backend(store):
    from impls.jax.backend import JaxBackend

    resolve_or_skip("jax:cpu")
    b = JaxBackend("cpu")
    b._store = store
    return b


def _run(b, scene, method="hybrid_secant", dtype="float64", **knobs):
    o, d = _rays()
    prep = b.prepare(method, scene, o, d, dtype=dtype, t_min=0.0, t_max=10.0, **knobs)
    return prep, prep.result(prep.run())


class UserSphere(Sphere):
    """A user's scene class: its code is outside isobench's packages."""


def test_a_value_digest_follows_the_value_and_refuses_code_it_cannot_see():
    a = executables.value_digest(Sphere(center=(0.0, 0.0, 0.0), radius=1.0))
    assert a is not None
    assert executables.value_digest(Sphere(center=(0.0, 0.0, 0.0), radius=1.0)) == a
    assert executables.value_digest(Sphere(center=(0.0, 0.0, 0.0), radius=1.0 + 2**-40)) != a
    assert executables.value_digest(Torus(major=1.0, minor=0.25)) not in (None, a)
    assert executables.value_digest(UserSphere(center=(0.0, 0.0, 0.0), radius=1.0)) is None
    assert executables.value_digest({"f": lambda x: x}) is None  # not picklable
    assert executables.value_digest({"f": _rays}) is None  # a function of a module outside the packages


@pytest.mark.slow  # compiles jax kernels
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_a_stored_kernel_runs_without_a_trace_and_gives_the_same_bits(dtype, tmp_path, monkeypatch):
    from impls.jax import backend as jb

    store = executables.KernelStore(tmp_path)
    scene = Torus(major=1.0, minor=0.3 + FRESH)
    first, want = _run(_backend(store), scene, dtype=dtype, xtol=1e-9)
    assert len(list(tmp_path.glob("*.bin"))) == 1

    def no_trace(*args, **kwargs):
        raise AssertionError("traced although the kernel store holds the kernel")

    # (a traced kernel is compiled by _compile_traced, or loaded by it from jax's persistent cache,
    # which also reads "reused": only the store's load skips it)
    monkeypatch.setattr(jb.JaxBackend, "compile", no_trace)
    monkeypatch.setattr(jb.JaxBackend, "_compile_traced", no_trace)
    again, got = _run(_backend(store), scene, dtype=dtype, xtol=1e-9)
    assert again.compile_cache == "reused"
    for k in ("t", "status", "iterations", "evals"):
        np.testing.assert_array_equal(getattr(got, k), getattr(want, k), err_msg=k)
    # a traced knob is still a runtime argument of the stored kernel
    _, other = _run(_backend(store), scene, dtype=dtype, xtol=1e-3)
    assert np.any(other.iterations != want.iterations)
    # a parameter of the scene is part of the key: a kernel of its own, traced
    monkeypatch.undo()
    _run(_backend(store), Torus(major=1.0, minor=0.31 + FRESH), dtype=dtype, xtol=1e-9)
    assert len(list(tmp_path.glob("*.bin"))) == 2


@pytest.mark.slow  # compiles jax kernels
def test_what_the_key_cannot_see_is_traced_and_never_stored(tmp_path):
    store = executables.KernelStore(tmp_path)
    _, want = _run(_backend(store), UserSphere(center=(0.0, 0.0, 0.0), radius=1.0 + 3 * FRESH))
    assert not list(tmp_path.glob("*.bin"))

    from impls.jax.backend import JaxBackend

    class UserJax(JaxBackend):
        pass

    resolve_or_skip("jax:cpu")
    b = UserJax("cpu")
    b._store = store
    _run(b, Sphere(center=(0.0, 0.0, 0.0), radius=1.0 + 2 * FRESH))
    assert not list(tmp_path.glob("*.bin"))


@pytest.mark.slow  # compiles jax kernels
def test_a_program_with_a_host_call_is_not_stored(tmp_path):
    from reference.cases import get_case

    case = get_case("mesh.torus.camera.16x16")
    store = executables.KernelStore(tmp_path)
    b = _backend(store)
    prep = b.prepare("sphere_trace", case.scene, case.origins[:64], case.directions[:64], dtype="float64",
                     t_min=case.t_min, t_max=case.t_max)
    prep.result(prep.run())
    assert not list(tmp_path.glob("*.bin"))


@pytest.mark.slow  # compiles jax kernels
def test_a_damaged_entry_is_a_miss_and_is_removed(tmp_path):
    store = executables.KernelStore(tmp_path)
    scene = Sphere(center=(0.0, 0.0, 0.0), radius=1.0 + FRESH)
    _, want = _run(_backend(store), scene)
    (entry,) = tmp_path.glob("*.bin")
    entry.write_bytes(b"not an executable")
    prep, got = _run(_backend(store), scene)
    np.testing.assert_array_equal(got.t, want.t)
    # (the kernel came from jax's persistent cache this time, which is not stored)
    assert not entry.exists() or entry.read_bytes() != b"not an executable"


def _entry(path):
    import pickle

    with open(path, "rb") as f:
        return pickle.load(f)


@pytest.mark.slow  # compiles jax kernels
def test_an_entry_is_checked_at_its_first_load_and_a_wrong_one_is_refused(tmp_path, monkeypatch):
    """A small configuration's entry carries its arrays and the compiled kernel's outputs; its
    first load runs the loaded executable on them: the same bits leave a ``.checked`` marker (later
    loads run nothing), other bits remove it and refuse its key, so that it is compiled, not
    stored, from then on."""
    import pickle

    from impls.jax import backend as jb

    store = executables.KernelStore(tmp_path)
    scene = Sphere(center=(0.0, 0.0, 0.0), radius=1.0 + 5 * FRESH)
    _, want = _run(_backend(store), scene)
    (path,) = tmp_path.glob("*.bin")
    args, outputs = _entry(path)["example"]
    assert len(outputs) >= 4 and args[0].shape == (64, 3)  # 48 rays padded to 64 rows
    good = path.read_bytes()

    def no_trace(*a, **k):
        raise AssertionError("traced although the kernel store holds the kernel")

    with monkeypatch.context() as m:
        m.setattr(jb.JaxBackend, "compile", no_trace)
        m.setattr(jb.JaxBackend, "_compile_traced", no_trace)
        prep, got = _run(_backend(store), scene)
    key = path.stem
    checked = tmp_path / f"{key}.checked"
    assert prep.compile_cache == "reused" and checked.exists()
    np.testing.assert_array_equal(got.t, want.t)
    with monkeypatch.context() as m:
        m.setattr(executables, "_same_outputs", no_trace)  # a checked entry is not run again
        prep, again = _run(_backend(store), scene)
    assert prep.compile_cache == "reused"
    np.testing.assert_array_equal(again.t, want.t)

    # an unchecked entry whose executable gives other bits than the kernel it was made from: refused
    entry = pickle.loads(good)
    entry["example"][1][0] = entry["example"][1][0] + 1
    path.write_bytes(pickle.dumps(entry))
    checked.unlink()
    assert store.load(key, _backend(store).jax_device) is None
    assert not path.exists() and (tmp_path / f"{key}.refused").exists()
    prep, got = _run(_backend(store), scene)
    np.testing.assert_array_equal(got.t, want.t)
    assert not path.exists()  # compiled again (or taken from jax's cache), and not stored


@pytest.mark.slow  # compiles jax kernels
def test_a_kernel_is_stored_at_its_first_call_with_that_calls_outputs(tmp_path, monkeypatch):
    """The entry is written when the kernel first runs, from that run's arguments and outputs: a
    cold configuration runs its kernel once, not once more to make the entry's example."""
    store = executables.KernelStore(tmp_path)
    calls = []
    real = executables.KernelStore.save
    monkeypatch.setattr(executables.KernelStore, "save",
                        lambda self, *a, **k: calls.append(k.get("outputs") is not None) or real(self, *a, **k))
    o, d = _rays()
    prep = _backend(store).prepare("hybrid_secant", Sphere(center=(0.0, 0.0, 0.0), radius=1.0 + 7 * FRESH), o, d,
                                   dtype="float64", t_min=0.0, t_max=10.0)
    assert prep.compile_cache == "compiled" and not calls and not list(tmp_path.glob("*.bin"))  # not yet run
    res = prep.result(prep.run())
    assert calls == [True]  # given the first call's outputs, so save runs nothing to make them
    (path,) = tmp_path.glob("*.bin")
    args, outputs = _entry(path)["example"]
    assert np.array_equal(args[0][:48], o) and np.array_equal(args[1][:48], d)
    assert any(np.array_equal(out[:48], res.t) for out in outputs if out.shape[:1] == (64,))
    prep.result(prep.run())
    assert calls == [True]  # once


@pytest.mark.slow  # compiles jax kernels
def test_a_large_configuration_is_checked_before_its_entry_is_written(tmp_path, monkeypatch):
    monkeypatch.setattr(executables, "EXAMPLE_BYTES", 0)
    store = executables.KernelStore(tmp_path)
    _run(_backend(store), Sphere(center=(0.0, 0.0, 0.0), radius=1.0 + 6 * FRESH))
    (path,) = tmp_path.glob("*.bin")
    assert _entry(path)["example"] is None


def test_the_key_changes_with_what_the_kernel_is_a_function_of():
    from impls.jax.backend import JaxBackend
    from impls.jax.driver import MaskedSettings

    resolve_or_skip("jax:cpu")
    b = JaxBackend("cpu")
    scene = Sphere(center=(0.0, 0.0, 0.0), radius=1.0)
    o = np.zeros((64, 3))
    base = dict(method="sphere_trace", scene=scene, t_range=(0.0, 10.0), extra={}, static={"bounds": 1},
                traced={"tol": 1e-6}, arrays=(o, o, None))
    key = executables.kernel_key(b, **base)
    assert key is not None and key == executables.kernel_key(b, **base)
    for change in (dict(method="march_newton"), dict(t_range=(0.0, 11.0)), dict(static={"bounds": 0}),
                   dict(traced={"tol": 1}), dict(traced={}), dict(arrays=(o[:32], o[:32], None)),
                   dict(arrays=(o.astype(np.float32), o.astype(np.float32), None)),
                   dict(scene=dataclasses.replace(scene, radius=2.0))):
        assert executables.kernel_key(b, **{**base, **change}) != key, change
    b2 = JaxBackend("cpu", MaskedSettings(ratio=2))
    assert executables.kernel_key(b2, **base) != key


@pytest.mark.slow  # compiles jax kernels
@pytest.mark.parametrize("large", [False, True], ids=["checked-at-load", "checked-before-write"])
def test_a_kernel_from_jax_persistent_cache_is_stored_from_the_bytes_jax_read(large, tmp_path, monkeypatch):
    """jax's executable loaded from its persistent cache serializes into bytes that fail when run
    (jax 0.10.2, CPU); the store makes its entry of the bytes jax read from its cache instead, so
    that a kernel whose program jax cached under another key of the store (code edited elsewhere)
    is stored at its first warm run, and the next run neither traces nor lowers it.  Both of the
    entry's checks (at its first load; before it is written) pass on those bytes, and the loaded
    kernel gives the compiled one's bits."""
    from impls.jax import backend as jb

    if not jb.PERSISTENT_CACHE:
        pytest.skip("no cache directory: jax's persistent cache is off")
    if large:
        monkeypatch.setattr(executables, "EXAMPLE_BYTES", 0)
    scene = Sphere(center=(0.0, 0.0, 0.0), radius=1.0 + (4 + large) * FRESH)
    _, want = _run(_backend(executables.KernelStore(tmp_path / "a")), scene)  # compiled: stored in a
    assert len(list((tmp_path / "a").glob("*.bin"))) == 1
    prep, got = _run(_backend(executables.KernelStore(tmp_path / "b")), scene)  # from jax's cache
    assert prep.compile_cache == "reused"
    (entry,) = (tmp_path / "b").glob("*.bin")  # stored from jax's bytes
    np.testing.assert_array_equal(got.t, want.t)

    def no_trace(*args, **kwargs):
        raise AssertionError("traced although the kernel store holds the kernel")

    monkeypatch.setattr(jb.JaxBackend, "_compile_traced", no_trace)
    prep, again = _run(_backend(executables.KernelStore(tmp_path / "b")), scene)
    assert prep.compile_cache == "reused" and entry.exists()
    assert not list((tmp_path / "b").glob("*.refused"))
    for k in ("t", "status", "iterations", "evals"):
        np.testing.assert_array_equal(getattr(again, k), getattr(want, k), err_msg=k)


def test_a_loaded_executable_serializes_only_from_the_bytes_it_was_loaded_from():
    """Why the store keeps the bytes jax read (:func:`impls.jax.executables.serialize`): an
    executable deserialized from bytes (as jax's persistent cache loads one) serializes, by jax's
    own ``serialize``, into bytes that do not run; made of the bytes it was loaded from, it runs.
    Should a jax version fix the former, this fails and the capture can go."""
    import jax
    import jax.numpy as jnp
    from jax.experimental import serialize_executable

    resolve_or_skip("jax:cpu")
    cpu = jax.devices("cpu")[0]
    x = np.linspace(0.0, 1.0, 5)
    # (a program of this session's: one jax's persistent cache held would be loaded from it, and
    # its own serialization, taken for the bytes below, would not run)
    compiled = jax.jit(lambda x: jnp.sum(jnp.isfinite(x)) + jnp.sum(x * (2.5 + FRESH))).lower(x).compile()
    want = np.asarray(compiled(x))
    raw = cpu.client.serialize_executable(compiled.runtime_executable())
    loaded = serialize_executable.deserialize_and_load(*executables.serialize(compiled), execution_devices=[cpu])
    try:
        broken = serialize_executable.deserialize_and_load(*executables.serialize(loaded), execution_devices=[cpu])
        broken(x)
    except Exception:  # noqa: BLE001 - the failure this documents
        broken = None
    assert broken is None
    again = serialize_executable.deserialize_and_load(*executables.serialize(loaded, raw), execution_devices=[cpu])
    np.testing.assert_array_equal(np.asarray(again(x)), want)


def test_the_store_drops_its_least_recently_used_entries_past_its_size(tmp_path):
    """Every edit of isobench's code changes every key, and a warm run stores its kernels anew:
    past ``max_bytes`` a prune removes the entries used longest ago (their modification times:
    a load marks its entry used, tested below) down to ``PRUNE_TO`` of it, with their ``.checked``
    markers; ``.refused`` markers stay."""
    store = executables.KernelStore(tmp_path, max_bytes=1000)
    for i, key in enumerate("abcdef"):
        (tmp_path / f"{key}.bin").write_bytes(b"x" * 200)  # 1,200 bytes in all
        os.utime(tmp_path / f"{key}.bin", (1000 + i, 1000 + i))  # a oldest … f newest
    (tmp_path / "a.checked").write_bytes(b"")
    (tmp_path / "b.refused").write_bytes(b"")
    os.utime(tmp_path / "b.bin", (2000, 2000))  # b used last
    assert store.prune() == 600  # to ≤ 750 bytes: a, c, d go (the oldest), b (used) stays
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.bin", "b.refused", "e.bin", "f.bin"]
    assert store.prune() == 0  # within the bound: nothing more


@pytest.mark.slow  # compiles jax kernels
def test_a_loaded_entry_is_the_last_to_be_pruned(tmp_path):
    store = executables.KernelStore(tmp_path)
    scene = Sphere(center=(0.0, 0.0, 0.0), radius=1.0 + 9 * FRESH)
    _run(_backend(store), scene)
    (entry,) = tmp_path.glob("*.bin")
    os.utime(entry, (1000, 1000))
    _run(_backend(store), scene)  # loaded from the store
    assert entry.stat().st_mtime > 1000
    size = entry.stat().st_size
    old = tmp_path / "0.bin"
    old.write_bytes(b"x" * size)
    os.utime(old, (1000, 1000))
    # 2 × size past 1.5 × size: pruned to 1.125 × size, the entry not loaded since goes
    assert executables.KernelStore(tmp_path, max_bytes=int(1.5 * size)).prune() == size
    assert entry.exists() and not old.exists()
