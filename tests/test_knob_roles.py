"""Knobs declare their role; suites sweep a knob by its role, never by its name."""

import pytest

from bench.suites import SUITES, default_sweep
from impls.methods import KNOB_ROLES, METHODS, Knob


def test_every_catalog_knob_declares_a_known_role():
    for spec in METHODS.values():
        for k in spec.knobs:
            assert k.role in KNOB_ROLES, (spec.name, k.name, k.role)


def test_a_knob_without_a_role_is_refused_naming_the_fix():
    with pytest.raises(ValueError, match=r"role=.*must be one of .*role='tolerance'"):
        Knob("tol", 1e-6, float, 0.0, "a tolerance")
    with pytest.raises(ValueError, match="role"):
        Knob("tol", 1e-6, float, 0.0, "a tolerance", role="accuracy")


@pytest.mark.parametrize("level", ["quick", "full"])
@pytest.mark.parametrize("main_dial_only", [True, False])
def test_every_swept_setting_is_valid_and_moves_only_tolerances_and_budgets(level, main_dial_only):
    # a name-based guess swept `bounds` (a 0/1 switch) to 2 and 4 and `ladder` to 1 (off): the sweep
    # must only produce settings the method accepts, and move only knobs whose role is swept
    for spec in METHODS.values():
        sweep = default_sweep(spec, level, main_dial_only)
        defaults = {k.name: k.default for k in spec.knobs}
        roles = {k.name: k.role for k in spec.knobs}
        for kd in sweep:
            spec.validate(kd)
            moved = {n for n, v in kd.items() if v != defaults[n]}
            assert {roles[n] for n in moved} <= {"tolerance", "budget"}, (spec.name, kd)


def test_a_role_decides_the_sweep_whatever_the_name():
    from impls.methods import MethodSpec

    spec = MethodSpec("m", "render", (Knob("gap", 1e-3, float, 0.0, "a tolerance named otherwise", role="tolerance"),
                                      Knob("xtol", 1e-3, float, 0.0, "a setting named like a tolerance", role="setting"),
                                      Knob("count", 16, int, 1, "a budget", role="budget"),
                                      Knob("mode", 3, int, 0, "an int setting", role="setting")), (), "")
    sweep = default_sweep(spec, "quick")
    assert {kd["gap"] for kd in sweep} == {1e-3, 1e-4, 1e-8, 1e-12}
    assert {kd["xtol"] for kd in sweep} == {1e-3}
    assert {kd["mode"] for kd in sweep} == {3}
    assert len({kd["count"] for kd in sweep}) > 1


def test_built_in_suites_sweep_only_the_main_dial():
    for suite in SUITES.values():
        for spec in METHODS.values():
            sweep = suite.sweep_for(spec)
            rest = [k.name for k in spec.knobs[1:]]
            assert all(kd[n] == sweep[0][n] for kd in sweep for n in rest), (suite.name, spec.name)
