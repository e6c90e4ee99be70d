"""Session 20, helper M20: (M6) magnetic_disturbance's windows for an intermittent disturbance — a magnet
at a fixed place visited several times (effects/magnet_intermittent.py, docs/diagnose.md §S20-M)."""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.diagnose.bench import simulated_session
from imugraph.diagnose.effects import magnetic_disturbance as md
from imugraph.diagnose.effects.base import envelope, replace_session
from imugraph.diagnose.fit import base_options, fit_base
from imugraph.diagnose.run import DiagnoseOptions, model_switches

# five visits (s after the start), each with its own body-frame field (the sensor near the magnet in
# another pose each time); the last one short (2.3 s: a visit the default's edge check is close to dropping)
VISITS = [((8.0, 15.0), 0.5, [0.6, -0.5, 0.6]), ((22.0, 27.0), 0.4, [0.0, 0.8, 0.6]),
          ((36.0, 42.0), 0.6, [-0.7, 0.1, 0.7]), ((50.0, 55.0), 0.45, [0.5, 0.5, -0.7]),
          ((63.0, 65.3), 0.5, [-0.3, -0.8, -0.5])]


@pytest.fixture(scope="module")
def visits():
    """75 s simulation (100 Hz) with the five VISITS (0.3 s raised-cosine ramps), its base fit, and the clean
    session's base fit."""
    s = simulated_session(11, 75.0, 100.0)
    F = float(np.nanmedian(np.linalg.norm(s.mag, axis=1)))
    t0 = float(s.t[0])
    mag = s.mag.copy()
    for (a, b), frac, d in VISITS:
        d = np.asarray(d, float) / np.linalg.norm(d)
        mag = mag + envelope(s.t, (t0 + a, t0 + b), 0.3)[:, None] * (frac * F * d)
    return (fit_base(replace_session(s, mag=mag), base_options(5.0)), fit_base(s, base_options(5.0)), t0)


def test_intermittent_search_finds_every_visit(visits, monkeypatch):
    """(M6) finds the five visits, each edge within 0.6 s of the ramp's centre; the default (at most 3
    windows, MAX_WINDOWS) cannot."""
    fit, _, t0 = visits
    monkeypatch.setattr(md, "INTERMITTENT", False)
    assert len(md.EFFECT.find_windows(fit)) <= md.MAX_WINDOWS < len(VISITS)
    monkeypatch.setattr(md, "INTERMITTENT", True)
    got = sorted((a - t0, b - t0) for a, b in md.EFFECT.find_windows(fit))
    assert len(got) == len(VISITS), got
    for (x, y), ((u, v), _, _) in zip(got, VISITS):
        assert abs(x - u) < 0.6 and abs(y - v) < 0.6, got


def test_intermittent_fit_removes_every_visit(visits, monkeypatch):
    """The (M1) fit on (M6)'s windows leaves a magnetometer residual inside the visits at the level of the
    residual outside them (RMS ratio < 1.5), where the default's fit leaves at least one visit unmodelled."""
    fit, _, t0 = visits
    t = fit.session.t
    inside = [(t >= t0 + a + 0.5) & (t <= t0 + b - 0.5) for (a, b), _, _ in VISITS]
    outside = ~np.any([(t >= t0 + a - 1) & (t <= t0 + b + 1) for (a, b), _, _ in VISITS], axis=0)

    def worst_ratio():
        corr = md.EFFECT.fit(fit, np.ones(fit.n, bool))
        r = corr.raw_residuals(fit)["mag"]
        rms = lambda m: float(np.sqrt(np.nanmean(np.sum(r[m] ** 2, axis=1))))  # noqa: E731
        return max(rms(m) for m in inside) / rms(outside)

    monkeypatch.setattr(md, "INTERMITTENT", False)
    assert worst_ratio() > 3.0
    monkeypatch.setattr(md, "INTERMITTENT", True)
    assert worst_ratio() < 1.5


def test_intermittent_search_finds_nothing_on_the_clean_session(visits, monkeypatch):
    _, clean, _ = visits
    monkeypatch.setattr(md, "INTERMITTENT", True)
    assert md.EFFECT.find_windows(clean) == []


def test_option_switches_and_restores_the_flag():
    before = md.INTERMITTENT
    with model_switches(DiagnoseOptions(magnet_intermittent=not before)):
        assert md.INTERMITTENT == (not before)
    assert md.INTERMITTENT == before


def test_visit_drift_follows_a_field_that_changes_through_the_window(monkeypatch):
    """(M7): a body-frame field growing linearly from 0.2 to 0.6 |m| over 20–40 s (the sensor edging closer
    to a magnet) is left in the residual by (M1)'s constant field (inside RMS > 2× outside) and removed by
    the Legendre drift (< 1.5×); with the flag off the columns are (M1)'s alone."""
    s = simulated_session(12, 60.0, 100.0)
    F = float(np.nanmedian(np.linalg.norm(s.mag, axis=1)))
    t0 = float(s.t[0])
    a, b = t0 + 20.0, t0 + 40.0
    ramp = np.clip((s.t - a) / (b - a), 0.0, 1.0)
    d = np.array([0.3, -0.6, 0.74]) / np.linalg.norm([0.3, -0.6, 0.74])
    field = np.where(((s.t >= a) & (s.t <= b))[:, None], (0.2 + 0.4 * ramp)[:, None] * F * d, 0.0)
    fit = fit_base(replace_session(s, mag=s.mag + field), base_options(5.0))
    t = fit.session.t
    inside, outside = (t >= a + 1) & (t <= b - 1), (t < a - 2) | (t > b + 2)

    def ratio():
        r = md.EFFECT.fit(fit, np.ones(fit.n, bool), window=(a, b)).raw_residuals(fit)["mag"]
        rms = lambda m: float(np.sqrt(np.nanmean(np.sum(r[m] ** 2, axis=1))))  # noqa: E731
        return rms(inside) / rms(outside)

    monkeypatch.setattr(md, "VISIT_DRIFT", False)
    assert ratio() > 2.0
    monkeypatch.setattr(md, "VISIT_DRIFT", True)
    assert ratio() < 1.5
