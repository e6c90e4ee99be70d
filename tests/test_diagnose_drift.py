"""gyro_bias_drift's spline basis (D2) (issue 5, S14-B; docs/diagnose.md §4 S14-B).

Known answers computed here independently of the code under test: the hat functions against numpy's
piecewise-linear interpolation, the spline's span (a ramp and a knot-resolved wander) against least
squares on the signal itself, and the joint estimator recovering an injected wander that the cubic (D1)
cannot hold.
"""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.diagnose.bench import simulated_session
from imugraph.diagnose.effects import EFFECTS
from imugraph.diagnose.effects import gyro_bias_drift as gbd
from imugraph.diagnose.effects.base import replace_session
from imugraph.diagnose.fit import fit_base
from imugraph.diagnose.run import DiagnoseOptions, model_switches
from imugraph.errors import SessionError


def test_hat_basis_is_linear_interpolation_between_knots():
    """(D2): β = B c equals np.interp through the knots (t0 → 0, t0 + kΔ → c_k); Δ from ⌈T / knot_s⌉."""
    t = np.linspace(3.0, 63.0, 2001)
    B = gbd.hat_basis(t, 3.0, 63.0, 10.0)
    assert B.shape == (2001, 6)                                   # 60 s / 10 s: 6 knots after t0
    c = np.array([0.3, -0.2, 0.5, 0.1, 0.0, 0.7])
    knots = 3.0 + 10.0 * np.arange(7)
    np.testing.assert_allclose(B @ c, np.interp(t, knots, np.r_[0.0, c]), atol=1e-12)
    assert np.all(B[0] == 0.0)                                    # β(t0) = 0: the constant is the base bias
    B7 = gbd.hat_basis(t, 3.0, 63.0, 9.0)                         # 60 / 9 → 7 knots, Δ = 60/7 s
    assert B7.shape[1] == 7
    np.testing.assert_allclose(B7.sum(axis=1)[t >= 3.0 + 60.0 / 7], 1.0, atol=1e-12)


def _share(B, y):
    """Fraction of y's variance (about its mean, the base model's constant) in the span of [1, B]."""
    A = np.column_stack([np.ones(len(y)), B])
    r = y - A @ np.linalg.lstsq(A, y, rcond=None)[0]
    return 1.0 - np.sum(r**2) / np.sum((y - y.mean())**2)


def test_spline_holds_a_ramp_exactly_and_a_wander_the_cubic_does_not():
    """Span: a ramp is in both bases; a wander of two sinusoids (periods 0.6 and 1.4 × the session, the
    injection's "wander" shape) is ≥ 95 % in the spline's span and < 80 % in the cubic's."""
    t = np.linspace(0.0, 60.0, 6001)
    x = t / 60.0
    ramp = x
    wander = np.sin(2 * np.pi * x / 0.6 + 1.0) + 0.5 * np.sin(2 * np.pi * x / 1.4 + 2.0)
    Bs = gbd.hat_basis(t, 0.0, 60.0, 10.0)
    Bl = gbd.legendre_basis(t, 0.0, 60.0)
    assert _share(Bs, ramp) > 1 - 1e-12 and _share(Bl, ramp) > 1 - 1e-12
    assert _share(Bs, wander) > 0.95
    assert _share(Bl, wander) < 0.8


@pytest.fixture(scope="module")
def wander_case():
    s = simulated_session(7, 30.0, 100.0)
    t = s.t
    knots = t[0] + (t[-1] - t[0]) * np.arange(4) / 3              # 30 s at ≈ 10 s: 3 knots after t0
    w = np.deg2rad(np.interp(t, knots, [0.0, 0.5, -0.2, 0.3]))    # a wander in (D2)'s span, 0.7 °/s p-p
    s2 = replace_session(s, gyr=s.gyr + np.outer(w, [1.0, 0.0, 0.0]))
    return s, fit_base(s), fit_base(s2), w


def _beta(fit, basis, monkeypatch):
    import imugraph.diagnose.effects.joint as joint

    monkeypatch.setattr(joint, "ENABLED", True)
    monkeypatch.setattr(gbd, "BASIS", basis)
    corr = EFFECTS["gyro_bias_drift"].fit(fit, np.ones(fit.n, bool))
    key = "spline_coefficients_rad_s" if basis == "spline" else "legendre_coefficients_rad_s"
    return gbd.drift_basis(fit.session.t) @ np.asarray(corr.params[key])


def test_joint_spline_drift_recovers_an_injected_wander(wander_case, monkeypatch):
    """Known answer: a piecewise-linear wander of 0.7 °/s p-p on x through knots 10 s apart (in (D2)'s
    span, not in the cubic's). The estimator is linear in the data, so the injected fit minus the host's
    own is the wander (less its mean: the base model's constant bias) within 0.05 °/s; the cubic's
    difference misses it by more."""
    s, f, f2, w = wander_case
    want = np.rad2deg(np.outer(w - w.mean(), [1.0, 0.0, 0.0]))
    err = {}
    for basis in ("spline", "legendre"):
        d = np.rad2deg(_beta(f2, basis, monkeypatch) - _beta(f, basis, monkeypatch))
        err[basis] = float(np.max(np.abs(d - d.mean(axis=0) - want)))
    assert err["spline"] < 0.05
    assert err["legendre"] > 2 * err["spline"]


def test_drift_basis_option_is_set_for_one_diagnosis_and_restored():
    """DiagnoseOptions.drift_basis switches the module's basis inside `model_switches` only; an unknown
    name is a SessionError naming the field."""
    before = gbd.BASIS
    with model_switches(DiagnoseOptions(drift_basis="spline")):
        assert gbd.BASIS == "spline"
    assert gbd.BASIS == before
    with pytest.raises(SessionError, match="drift_basis"):
        with model_switches(DiagnoseOptions(drift_basis="fourier")):
            pass
    assert gbd.BASIS == before
