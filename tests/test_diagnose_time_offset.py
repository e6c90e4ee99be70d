"""time_offset's delay search (issue 5, speed and the held-out blocks): the normal-equation form of the
gyro-referenced delay (T3, calibration.alignment.estimate_mag_delay) against one least squares per lag
written out here, its known answer on a
delayed simulation with and without the cross-validation's hidden blocks, and the first-order floor (T4)
that lets the fit skip the gyro candidates: a true lower bound, and skipping changes no fitted result."""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.calibration.alignment import estimate_mag_delay
from imugraph.diagnose.attribute import AttributionOptions, fold_masks
from imugraph.diagnose.bench import simulated_session
from imugraph.diagnose.effects import time_offset as to
from imugraph.diagnose.effects.base import replace_session, shift_signal
from imugraph.diagnose.fit import fit_base

TAU = 0.02           # injected delay, s (2 samples at 100 Hz)


@pytest.fixture(scope="module")
def sim():
    return simulated_session(7, 40.0, 100.0)


@pytest.fixture(scope="module")
def fits(sim):
    """Base fits of the simulation unmodified and with the accelerometer / the gyro delayed by TAU."""
    out = {"clean": fit_base(sim)}
    for c in ("acc", "gyr"):
        out[c] = fit_base(replace_session(sim, **{c: shift_signal(sim.t, getattr(sim, c), TAU)}))
    return out


def _per_lag_delay(t, y, b_gyr, max_delay_s, window_s=0.04, max_rows=4000):
    """Reference: for every lag of the grid, a free 3×3 A fitted to Δy_j ≈ [y_j]× A ΔΩ_j(τ) by its own
    least squares (the textbook form of (T3); gap-free data), minimum refined by a parabola."""
    from imugraph.geometry import skew

    h = max(1, int(round(0.5 * window_s / float(np.median(np.diff(t))))))
    lo, mid, hi = np.arange(0, t.size - 2 * h), np.arange(h, t.size - h), np.arange(2 * h, t.size)
    keep = np.linspace(0, mid.size - 1, min(mid.size, max_rows)).round().astype(int)
    lo, mid, hi = lo[keep], mid[keep], hi[keep]
    dy = y[hi] - y[lo]
    omega = np.concatenate([np.zeros((1, 3)), np.cumsum(b_gyr[:-1] * np.diff(t)[:, None], axis=0)])
    step = float(np.median(np.diff(t)))
    taus = np.arange(-max_delay_s, max_delay_s + 0.5 * step, step)
    rss = []
    for tau in taus:
        d_om = np.stack([np.interp(t[hi] - tau, t, omega[:, i]) - np.interp(t[lo] - tau, t, omega[:, i])
                         for i in range(3)], axis=1)
        rows = np.einsum("nik,nl->nikl", skew(y[mid]), d_om).reshape(-1, 9)
        sol = np.linalg.lstsq(rows, dy.reshape(-1), rcond=None)[0]
        rss.append(float(np.sum((dy.reshape(-1) - rows @ sol) ** 2)))
    r = np.array(rss)
    k = int(np.argmin(r))
    return float(taus[k] + 0.5 * step * (r[k - 1] - r[k + 1]) / (r[k - 1] - 2 * r[k] + r[k + 1]))


def test_normal_equations_equal_one_least_squares_per_lag(sim):
    """(T3) solves the same least squares as one fit per lag on gap-free data: same τ to rounding, and
    both find the injected delay of gravity seen by the accelerometer (pure rotation: gravity only)."""
    acc = shift_signal(sim.t, sim.acc, TAU)
    w = sim.gyr - np.median(sim.gyr[:50], axis=0)
    ref = _per_lag_delay(sim.t, acc, w, max_delay_s=0.1)
    new = estimate_mag_delay(sim.t, acc, w, max_delay_s=0.1)
    assert abs(new - ref) < 1e-9
    assert abs(new - TAU) < 3e-3


def test_hidden_blocks_do_not_bend_the_delay(sim):
    """Training samples of each cross-validation fold (the held-out 2 s blocks set to NaN): the windows
    spanning a hidden block are dropped, so every fold finds the injected delay."""
    acc = shift_signal(sim.t, sim.acc, TAU)
    w = sim.gyr - np.median(sim.gyr[:50], axis=0)
    for fold in fold_masks(sim.t, AttributionOptions()):
        tau = estimate_mag_delay(sim.t, np.where(fold[:, None], np.nan, acc), w, max_delay_s=0.1)
        assert abs(tau - TAU) < 3e-3, tau


def _floor_terms(fit, train):
    """r₀ and J = ∂r/∂τ of a gyro shift, as TimeOffset.fit builds them at τ = 0."""
    from imugraph.diagnose.effects.base import gyro_refit

    s = fit.session
    r1 = gyro_refit(fit, np.nan_to_num(np.gradient(s.gyr, s.t, axis=0)))[0]
    J = {k: r1[k] - fit.residuals[k] for k in ("gyr", "acc", "mag")}
    return fit.residuals, J


@pytest.mark.parametrize("name", ["clean", "acc", "gyr"])
def test_first_order_floor_is_below_every_exact_gyro_shift(fits, name):
    """(T4) is a lower bound of the exact relative cost of shifting the gyro, for shifts from −30 to
    +30 ms (the exact cost comes from the re-integration, not from the first-order form)."""
    fit = fits[name]
    train = np.ones(fit.n, bool)
    ch = ("gyr", "acc", "mag")
    r0, J = _floor_terms(fit, train)
    floor = to._first_order_floor(fit, r0, J, train, ch)
    assert floor <= 3.0 + 1e-9                       # q(0) = 3: no shift at all
    for tau in (-0.03, -0.01, -0.003, 0.003, 0.01, 0.02, 0.03):
        corr = to.TimeOffsetCorrection("time_offset", {"channel": "gyr", "tau_s": tau}, 2, channel="gyr")
        exact = to._relative_cost(fit, corr.raw_residuals(fit), train, ch)
        assert exact >= floor - 1e-9, (tau, exact, floor)


@pytest.mark.parametrize("name", ["clean", "acc", "gyr"])
def test_skipping_the_gyro_candidates_changes_no_fit(fits, name, monkeypatch):
    """The fit with the floor (T4) equals the fit that evaluates every gyro candidate exactly, on all
    samples and on a fold's training samples."""
    fit = fits[name]
    folds = fold_masks(fit.session.t, AttributionOptions())
    for train in (np.ones(fit.n, bool), ~folds[2]):
        fast = to.EFFECT.fit(fit, train)
        with monkeypatch.context() as m:
            m.setattr(to, "_first_order_floor", lambda *a, **k: -np.inf)
            full = to.EFFECT.fit(fit, train)
        assert fast.params["channel"] == full.params["channel"]
        assert fast.params["tau_s"] == pytest.approx(full.params["tau_s"], abs=1e-12)
