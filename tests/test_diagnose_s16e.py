"""Session 16, helper E: (M3') the magnet's step search after the (M1) fit of the windows found, and (C1')
the censored gyro residual of saturation (docs/diagnose.md §S16-E)."""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.diagnose.bench import simulated_session
from imugraph.diagnose.effects import magnetic_disturbance as md
from imugraph.diagnose.effects import saturation as sat
from imugraph.diagnose.effects.base import envelope, replace_session
from imugraph.diagnose.fit import base_options, fit_base
from imugraph.diagnose.run import DiagnoseOptions, model_switches


@pytest.fixture(scope="module")
def strong_magnet():
    """60 s simulation (100 Hz) with a strong body-frame magnet (1.2 |m|, 0.45 s raised-cosine ramps) over
    44–54 s — the shape of harness seed 1 case 001 (1.35 |m| over the last sixth of a crop) — and its base fit."""
    s = simulated_session(7, 60.0, 100.0)
    F = float(np.nanmedian(np.linalg.norm(s.mag, axis=1)))
    vec = 1.2 * F * np.array([0.55, -0.65, 0.52]) / np.linalg.norm([0.55, -0.65, 0.52])
    t0 = float(s.t[0])
    win = (t0 + 44.0, t0 + 54.0)
    s2 = replace_session(s, mag=s.mag + envelope(s.t, win, 0.45)[:, None] * vec)
    return fit_base(s2, base_options(5.0)), win


def test_step_refit_finds_the_strong_magnet_alone(strong_magnet, monkeypatch):
    """(M3'): with the (M1) fit between searches the windows are the magnet's alone, both edges within
    0.5 s (the ramps' centres); the effect's reported window (t_start, t_end) is that window."""
    fit, (a, b) = strong_magnet
    monkeypatch.setattr(md, "STEP_REFIT", True)
    wins = md.EFFECT.find_windows(fit)
    assert len(wins) == 1, wins
    assert abs(wins[0][0] - a) < 0.5 and abs(wins[0][1] - b) < 0.5, wins
    corr = md.EFFECT.fit(fit, np.ones(fit.n, bool))
    assert abs(corr.t_start - a) < 0.5 and abs(corr.t_end - b) < 0.5


def test_step_refit_finds_two_windows_and_none_on_clean():
    """(M3') keeps finding a second, separate magnet (0.3 |m| over 10–20 s beside 0.8 |m| over 35–45 s) and
    finds nothing on the clean simulation."""
    s = simulated_session(8, 60.0, 100.0)
    F = float(np.nanmedian(np.linalg.norm(s.mag, axis=1)))
    t0 = float(s.t[0])
    clean = fit_base(s, base_options(5.0))
    earth = F
    found, _ = md.step_windows_refit(clean, clean.residuals["mag"], earth)
    assert found == []
    mag = s.mag + envelope(s.t, (t0 + 10, t0 + 20), 0.3)[:, None] * (0.3 * F * np.array([0.0, 0.6, 0.8])) \
        + envelope(s.t, (t0 + 35, t0 + 45), 0.3)[:, None] * (0.8 * F * np.array([0.8, 0.0, -0.6]))
    fit = fit_base(replace_session(s, mag=mag), base_options(5.0))
    found, _ = md.step_windows_refit(fit, fit.residuals["mag"], earth)
    got = sorted((float(s.t[i0]) - t0, float(s.t[min(i1, s.n) - 1]) - t0) for i0, i1 in found)
    assert len(got) == 2, got
    for (x, y), (u, v) in zip(got, [(10, 20), (35, 45)]):
        assert abs(x - u) < 0.6 and abs(y - v) < 0.6, got


def test_censored_gyro_known_answers():
    """(C1'): on a +rail at L = 2 the residual is NaN where the fit's ω̂ ≥ L and L − ω̂ where ω̂ < L; on a
    −rail the mirror; samples off the rail keep their residual."""
    y = np.array([[2.0, 0, 0], [2.0, 0, 0], [1.0, -3.0, 0], [0.5, -3.0, 0]])
    y_new = y + np.array([[0.4, 0, 0], [0.1, 0, 0], [0, -0.2, 0], [0, -0.5, 0]])
    pred = np.array([[2.3, 0, 0], [1.8, 0, 0], [0.9, -3.1, 0], [0.4, -2.9, 0]])
    r = y_new - pred
    rails = [(0, 1.0, 2.0), (1, -1.0, -3.0)]
    out = sat.censored_gyro(y, y_new, r, rails)
    assert np.isnan(out[0, 0]) and out[1, 0] == pytest.approx(2.0 - 1.8)
    assert np.isnan(out[2, 1]) and out[3, 1] == pytest.approx(-3.0 - (-2.9))
    np.testing.assert_allclose(out[2:, 0], r[2:, 0])
    np.testing.assert_allclose(out[:, 2], r[:, 2])


def test_options_switch_and_restore_the_flags():
    before = (md.STEP_REFIT, sat.CENSOR_GYRO)
    with model_switches(DiagnoseOptions(magnet_step_refit=not before[0], saturation_censor=not before[1])):
        assert (md.STEP_REFIT, sat.CENSOR_GYRO) == (not before[0], not before[1])
    assert (md.STEP_REFIT, sat.CENSOR_GYRO) == before
    assert before == (True, True)                        # the defaults since session 16


def test_censored_values_match_the_keyframes_and_stay_beyond_the_rail():
    """(C1''): a simulation's gyro clipped so ≈ 2 % of samples exceed the rail. With the keyframes of the
    base fit of the clipped data fixed, the per-interval estimate (i) keeps every censored value at or
    beyond its rail and (ii) lowers the whitened gyro residual of the unclipped samples in the intervals that
    hold clipped ones. (Whether it recovers the TRUE censored area is not asserted: it does not reliably,
    benchmarks/e5_censored_area.py, docs/diagnose.md §S16-E.)"""
    from imugraph.diagnose.effects.trajectory import gyro_exact

    s = simulated_session(3, 40.0, 100.0)
    level = float(np.quantile(np.max(np.abs(s.gyr), axis=1), 0.98))
    clipped = replace_session(s, gyr=np.clip(s.gyr, -level, level))
    fit = fit_base(clipped, base_options(5.0))
    rails = sat.find_rails(clipped.gyr, np.ones(fit.n, bool))
    assert rails
    y_q = sat.reconstruct_peaks(clipped.t, clipped.gyr, rails)
    y_c = sat.censored_values(fit, y_q, rails)
    k_of = sat._intervals(fit)
    hit = np.zeros(fit.n, bool)
    for a, sign, lv in rails:
        m = sat.on_rail(clipped.gyr[:, a], lv)
        hit |= m
        assert np.all(sign * (y_c[m, a] - lv) >= -1e-12)                                    # (i)
    iv = np.isin(k_of, np.unique(k_of[hit])) & ~hit
    sig = np.asarray(fit.sigma["gyr"], float)
    rms = [float(np.sqrt(np.nanmean((gyro_exact(fit, y - clipped.gyr)["gyr"][iv] / sig) ** 2))) for y in (y_q, y_c)]
    assert rms[1] < 0.7 * rms[0], rms                                                           # (ii)


@pytest.mark.parametrize("seed", [7, 11])
def test_a_window_at_the_end_is_the_shorter_side(seed):
    """(M3) scores a window touching an end exactly as its complement; the shorter side is the disturbance
    (review R2: a magnet over the last 10 s of 60 s was reported as the first 50 s on some seeds)."""
    rng = np.random.default_rng(seed)
    rate = 100.0
    t = np.arange(0.0, 60.0, 1.0 / rate)
    r = rng.normal(0.0, 0.02, (len(t), 3))
    r[t >= 50.0] += [0.6, -0.4, 0.3]
    wins = md.step_windows(t, r, 1.0)
    assert wins, "the step is found"
    i0, i1 = wins[0][0], wins[0][1]
    assert t[i0] > 45.0 and i1 >= len(t) - 200
