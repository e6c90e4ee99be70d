"""Session 20, helper M20b: what the full refit (F1) changes in the gyro fit (imugraph.diagnose.refit,
docs/diagnose.md §S20-Mb) — the refit machinery alone changes nothing; the alternation re-estimates the
noise levels (a removed magnet lowers σ_mag); `refit.HOLD_NOISE` (opt-in) holds them at the base fit's."""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.diagnose import refit as rf
from imugraph.diagnose.bench import simulated_session
from imugraph.diagnose.effects import magnetic_disturbance as md
from imugraph.diagnose.effects.base import envelope, replace_session
from imugraph.diagnose.fit import base_options, fit_base, fit_simulation
from imugraph.diagnose.run import DiagnoseOptions, model_switches

WINDOW = (15.0, 25.0)          # s after the start: a magnet attached to the sensor, 0.5 |m| (body frame)


@pytest.fixture(scope="module")
def magnet():
    """40 s simulation (100 Hz) with a 0.5 |m| body-frame field over WINDOW (0.3 s ramps) and its base fit."""
    s = simulated_session(7, 40.0, 100.0)
    F = float(np.nanmedian(np.linalg.norm(s.mag, axis=1)))
    t0 = float(s.t[0])
    d = np.array([0.6, -0.5, 0.6]) / np.linalg.norm([0.6, -0.5, 0.6])
    mag = s.mag + envelope(s.t, (t0 + WINDOW[0], t0 + WINDOW[1]), 0.3)[:, None] * (0.5 * F * d)
    return fit_base(replace_session(s, mag=mag), base_options(5.0)), s


@pytest.fixture(scope="module")
def magnet_fit(magnet):
    return magnet[0]


def _gyro_rms(fit, sigma) -> float:
    return float(np.sqrt(np.nanmean((fit.residuals["gyr"] / sigma) ** 2)))


def test_null_refit_keeps_the_base_fit(magnet_fit):
    magnet = magnet_fit
    """The refit machinery (fit_simulation from the base fit) on the UNCHANGED data returns the base fit:
    gyro whitened RMS and every noise level within 2 %. (BROAD 28: 31.4 → 31.3 outside the magnet, so the
    refit's change there is not the machinery's.)"""
    null = rf.on_session(fit_simulation(magnet.session, magnet), magnet.session)
    sg = np.asarray(magnet.sigma["gyr"], float)
    assert abs(_gyro_rms(null, sg) / _gyro_rms(magnet, sg) - 1.0) < 0.02
    for c in ("acc", "mag"):
        np.testing.assert_allclose(null.calibration.noise[c], magnet.calibration.noise[c], rtol=0.02)


def test_default_refit_reestimates_the_magnetometer_sigma(magnet_fit, monkeypatch):
    magnet = magnet_fit
    """By default the alternation re-estimates the noise: the magnet inflated the base fit's σ_mag, the
    refit of the data with its field removed has a smaller one (what reweights the trajectory on BROAD 28)."""
    monkeypatch.setattr(rf, "HOLD_NOISE", False)
    assert rf.refit_options(magnet) is None
    ext, info = md.EFFECT.refit(magnet, 2)
    assert info["changed"]
    base = np.linalg.norm(magnet.calibration.noise["mag"])
    assert np.linalg.norm(ext.calibration.noise["mag"]) < 0.8 * base


def test_hold_noise_keeps_the_base_noise_levels(magnet_fit, monkeypatch):
    magnet = magnet_fit
    """HOLD_NOISE: the refit's noise levels are exactly the base fit's, and its gyro fit is not worse than
    the default refit's (less weight on the magnetometer)."""
    monkeypatch.setattr(rf, "HOLD_NOISE", False)
    ext_default, _ = md.EFFECT.refit(magnet, 2)
    monkeypatch.setattr(rf, "HOLD_NOISE", True)
    assert rf.refit_options(magnet).reestimate_noise is False
    ext, info = md.EFFECT.refit(magnet, 2)
    assert info["changed"]
    for c in ("gyr", "acc", "mag"):
        np.testing.assert_array_equal(ext.calibration.noise[c], magnet.calibration.noise[c])
    sg = np.asarray(magnet.sigma["gyr"], float)
    assert _gyro_rms(ext, sg) <= 1.05 * _gyro_rms(ext_default, sg)


def test_option_switches_and_restores_the_flag():
    saved = rf.HOLD_NOISE
    with model_switches(DiagnoseOptions(refit_hold_noise=True)):
        assert rf.HOLD_NOISE is True
    assert rf.HOLD_NOISE == saved
    with model_switches(DiagnoseOptions()):
        assert rf.HOLD_NOISE == saved


def test_accelerated_refit_reaches_the_clean_data_refit(magnet, monkeypatch):
    """(F2): the alternation's θ* on the magnet session against the refit of the CLEAN session (the field
    removed exactly, same start): the default two rounds leave θ*'s gyro fit more than twice as bad (the
    slow linear convergence of the coupled field and heading); the Aitken jump brings it within 10 %."""
    fit, clean = magnet
    sg = np.asarray(fit.sigma["gyr"], float)
    target = _gyro_rms(rf.on_session(fit_simulation(clean, fit), fit.session), sg)
    monkeypatch.setattr(rf, "ACCELERATE", False)
    slow, _ = md.EFFECT.refit(fit, 2)
    assert _gyro_rms(slow, sg) > 2.0 * target
    monkeypatch.setattr(rf, "ACCELERATE", True)
    fast, info = md.EFFECT.refit(fit, 2)
    assert info.get("extrapolated") and 0.0 < info["rho"] < rf.RHO_MAX
    assert _gyro_rms(fast, sg) < 1.10 * target


def test_aitken_step_on_a_geometric_sequence():
    """_aitken: y_r = y_∞ + ρ^r e (known ρ = 0.6) extrapolates to y_∞ exactly; NaN rows stay NaN."""
    y_inf, e = np.arange(12.0).reshape(4, 3), np.ones((4, 3))
    seq = [{"mag": y_inf + 0.6 ** r * e} for r in (1, 2, 3)]
    for y in seq:
        y["mag"][0] = np.nan                   # a sample left out in every round (FieldRemoved's edges)
    jump, rho = rf._aitken(seq)
    assert rho == pytest.approx(0.6)
    np.testing.assert_allclose(jump["mag"][1:], y_inf[1:])
    assert np.all(np.isnan(jump["mag"][0]))
    assert rf._aitken([{"mag": y_inf}, {"mag": y_inf}, {"mag": y_inf}])[0] is None      # no step: ρ undefined


def test_accelerate_option_switches_the_flag():
    saved = rf.ACCELERATE
    with model_switches(DiagnoseOptions(refit_accelerate=True)):
        assert rf.ACCELERATE is True
    assert rf.ACCELERATE == saved
