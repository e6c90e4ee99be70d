"""Diagnosis core (issue 5): base fit, simulation from the fit, gap statistic, localisation, attribution,
report and command. Simulated sessions are short (30 s at 100 Hz); one real-data test skips without data."""

from __future__ import annotations

import argparse
import functools
import json

import numpy as np
import pytest

from imugraph.diagnose import gap as G
from imugraph.diagnose.attribute import AttributionOptions, attribute, fold_masks, verdict
from imugraph.diagnose.fit import body_rate, fit_base, fit_simulation, simulate_from_fit
from imugraph.geometry import quat_to_rotmat
from imugraph.io.session import Session
from imugraph.sim.motion import random_rotation_motion
from imugraph.sim.sensors import SensorParams, simulate_imu

PARAMS = SensorParams(gyro_bias=[0.01, -0.02, 0.005], gyro_noise=0.005, acc_noise=0.05, mag_noise=0.01,
                      mag_D=np.diag([1.1, 0.9, 1.0]), mag_o=[0.2, -0.1, 0.05])


def model_session(seed: int, duration: float = 30.0) -> Session:
    rng = np.random.default_rng(seed)
    return simulate_imu(*random_rotation_motion(duration, 100, rng, pauses=2), PARAMS, rng)


@pytest.fixture(scope="module")
def fits():
    """Fit of a session drawn from the base model, and of two simulations from that fit."""
    s = model_session(0)
    real = fit_base(s)
    rng = np.random.default_rng(10)
    return real, fit_simulation(simulate_from_fit(real, rng), real), fit_simulation(simulate_from_fit(real, rng), real)


# ------------------------------------------------------------------------------------------ gap statistic
def test_wasserstein_known_answers():
    rng = np.random.default_rng(1)
    a = rng.standard_normal(20000)
    # a shift by c moves every quantile by c: W1 = c exactly
    assert G.wasserstein1(a, a + 0.7) == pytest.approx(0.7, abs=1e-9)
    # N(0,1) vs N(0,s²): W1 = |s − 1|·E|z| = |s − 1|·√(2/π)
    assert G.wasserstein1(a, 2.0 * a) == pytest.approx(np.sqrt(2 / np.pi), rel=0.03)


def test_autocorrelation_of_ar1_and_masks():
    rng = np.random.default_rng(2)
    phi, n = 0.8, 40000
    e = rng.standard_normal((n, 3))
    x = np.zeros((n, 3))
    for i in range(1, n):
        x[i] = phi * x[i - 1] + e[i]
    lags = np.array([1, 2, 5])
    rho = G.autocorrelation(x, np.ones(n, bool), lags)
    np.testing.assert_allclose(rho, np.repeat((phi ** lags)[:, None], 3, 1), atol=0.03)
    # half the samples masked out in blocks: the pairs crossing a gap are not used, ρ is unchanged
    mask = (np.arange(n) // 1000) % 2 == 0
    np.testing.assert_allclose(G.autocorrelation(x, mask, lags), rho, atol=0.04)


def test_channel_gap_zero_for_same_distribution_large_for_colour_and_scale():
    rng = np.random.default_rng(3)
    n = 20000
    m = np.ones(n, bool)
    lags = G.lag_grid(100.0, G.GapOptions())
    white1, white2 = rng.standard_normal((n, 3)), rng.standard_normal((n, 3))
    same = G.channel_gap(white1, white2, m, lags)
    scaled = G.channel_gap(1.5 * white1, white2, m, lags)
    # moving sum of 30 white samples / √30: unit variance, correlated over 30 samples
    coloured = np.stack([np.convolve(rng.standard_normal(n), np.ones(30) / np.sqrt(30), "same")
                         for _ in range(3)], 1)
    col = G.channel_gap(coloured, white2, m, lags, parts=True)
    assert same < 0.05
    assert scaled > 0.3
    assert col[2] > 10 * same          # the whiteness term sees the colour


def test_localise_finds_a_burst():
    rng = np.random.default_rng(4)
    t = np.arange(0, 120, 0.01)
    n = len(t)
    real = {c: rng.standard_normal((n, 3)) for c in G.CHANNELS}
    sim = {c: rng.standard_normal((n, 3)) for c in G.CHANNELS}
    null = {c: rng.standard_normal((n, 3)) for c in G.CHANNELS}
    inside = (t >= 50) & (t < 70)
    real["mag"][inside] += 2.0
    sigma = {c: np.ones(3) for c in G.CHANNELS}
    rc = G.gap_curve(real, sim, sigma, t)
    nc = G.gap_curve(null, sim, sigma, t)
    _, locs = G.localise(t, rc, nc)
    assert locs and locs[0]["channel"] == "mag"
    assert abs(locs[0]["t_start"] - 50) < 3.5 and abs(locs[0]["t_end"] - 70) < 3.5
    assert all(loc["channel"] == "mag" for loc in locs)


# ------------------------------------------------------------------------------------------------ the fit
def test_body_rate_recovers_the_simulated_rate():
    rng = np.random.default_rng(5)
    m = random_rotation_motion(10, 100, rng)
    w = body_rate(quat_to_rotmat(m.nRb), np.full(len(m.t), 0.01))
    np.testing.assert_allclose(w[:-1], m.b_omega[:-1], atol=1e-6)


def test_fit_recovers_model_and_residuals_match_truth(fits):
    real, _, _ = fits
    s = real.session
    cal = real.calibration
    np.testing.assert_allclose(cal.gyro_bias, PARAMS.gyro_bias, atol=2e-3)
    for c, sig in (("acc", PARAMS.acc_noise), ("mag", PARAMS.mag_noise)):
        np.testing.assert_allclose(real.sigma[c], sig, rtol=0.15)
    # residuals computed independently from the truth orientation: acc − R_trueᵀ(0,0,g) ≈ noise
    R_true = quat_to_rotmat(s.quat)
    acc_true = s.acc - np.einsum("nji,j->ni", R_true, np.array([0, 0, PARAMS.g]))
    assert np.std(real.residuals["acc"]) == pytest.approx(np.std(acc_true), rel=0.1)
    # definition (R3) by hand at a few samples
    for j in (0, 777, s.n - 1):
        h = cal.D @ real.nRb[j].T @ cal.n_mag + cal.o
        np.testing.assert_allclose(real.residuals["mag"][j], s.mag[j] - h, atol=1e-12)
    assert np.isnan(real.residuals["gyr"][-1]).all()


def test_simulation_from_fit_follows_the_fitted_model(fits):
    real, _, _ = fits
    sim = simulate_from_fit(real, np.random.default_rng(7))
    assert sim.n == real.n and np.array_equal(np.isnan(sim.mag), np.isnan(real.session.mag))
    bRn = np.transpose(real.nRb, (0, 2, 1))
    e_acc = sim.acc - bRn @ np.array([0, 0, real.g])
    np.testing.assert_allclose(np.std(e_acc, 0), real.calibration.noise["acc"], rtol=0.05)
    e_gyr = sim.gyr - real.b_omega - real.b_gyr_bias
    np.testing.assert_allclose(np.std(e_gyr[:-1], 0), real.calibration.noise["gyr"], rtol=0.05)
    np.testing.assert_allclose(np.mean(e_gyr, 0), 0, atol=3 * real.calibration.noise["gyr"].max() / np.sqrt(sim.n))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_gap_near_zero_when_data_come_from_the_model(seed):
    """Simulate from a model, fit, simulate from the fit: gap below the detection floor on every channel."""
    real = fit_base(model_session(seed))
    rng = np.random.default_rng(100 + seed)
    a = fit_simulation(simulate_from_fit(real, rng), real)
    b = fit_simulation(simulate_from_fit(real, rng), real)
    g = G.gap(real.residuals, a.residuals, real.sigma, real.session.rate)
    null = G.gap(b.residuals, a.residuals, real.sigma, real.session.rate)
    floor = AttributionOptions().min_gap_ratio
    for c in G.CHANNELS:
        assert g[c] < floor * null[c], (c, g[c], null[c])


# ------------------------------------------------------------------------------------------- attribution
class _Corr:
    def __init__(self, name, res, n_params, window=(None, None), params=None):
        self.name, self._res, self.n_params = name, res, n_params
        self.t_start, self.t_end = window
        self.params = params or {}

    def residuals(self, fit):
        return self._res

    raw_residuals = residuals          # no noise re-estimation in a stub: raw and rescaled are the same


class StubOffset:
    """Windowed magnetometer offset (test stub): mean mag residual inside and outside the window (the base
    fit absorbed part of the disturbance into o), training samples only."""

    name, channel, windowed = "stub_offset", "mag", True

    def fit(self, fit, train, window=None):
        t = fit.session.t
        a, b = window if window is not None else (t[0], t[-1])
        inside = (t >= a) & (t <= b)
        r = fit.residuals["mag"]
        off = np.nanmean(r[inside & train], axis=0)
        base = np.nanmean(r[~inside & train], axis=0)
        res = {c: fit.residuals[c].copy() for c in G.CHANNELS}
        res["mag"][inside] -= off
        res["mag"][~inside] -= base
        return _Corr(self.name, res, 6, (a, b), {"offset": (off - base).tolist()})


class StubNothing:
    """An effect that changes nothing (its penalised shrink must be ≤ 0)."""

    name, channel, windowed = "stub_nothing", "acc", False

    def fit(self, fit, train, window=None):
        return _Corr(self.name, {c: fit.residuals[c].copy() for c in G.CHANNELS}, 3)


def _disturbed(seed=11):
    s = model_session(seed, duration=40.0)
    mag = s.mag.copy()
    inside = (s.t >= 15) & (s.t < 27)
    mag[inside] += np.array([0.3, -0.2, 0.25])            # a magnet: 30 % of the field
    return Session(s.t, s.gyr, s.acc, mag, s.quat, s.movement, s.source, "disturbed", dict(s.meta))


def test_folds_interleave_and_cover():
    t = np.arange(0, 50, 0.01)
    folds = fold_masks(t, AttributionOptions(n_folds=5, block_s=2.0))
    assert np.array_equal(np.sum(folds, axis=0), np.ones(len(t)))
    for f in folds:       # every fold spans the recording
        assert t[f].min() < 10 and t[f].max() > 40


def _residual_fit(res: dict, t: np.ndarray):
    """A Fit-like object holding residuals only (what the attribution reads)."""
    from types import SimpleNamespace

    sess = SimpleNamespace(t=t, rate=float(1 / np.median(np.diff(t))), n=len(t))
    return SimpleNamespace(residuals=res, sigma={c: np.ones(3) for c in G.CHANNELS}, session=sess, n=len(t))


def test_attribution_on_known_residuals():
    """Real residuals = white noise + an offset in a window; the windowed stub explains it on held-out
    blocks, the do-nothing stub does not; pure noise gives the verdict none."""
    rng = np.random.default_rng(8)
    t = np.arange(0, 100, 0.01)
    white = lambda: {c: rng.standard_normal((len(t), 3)) for c in G.CHANNELS}   # noqa: E731
    real_r, sim_r, null_r = white(), white(), white()
    real_r["mag"][(t >= 40) & (t <= 60)] += np.array([2.0, -1.0, 1.6])
    real, sim, null = _residual_fit(real_r, t), _residual_fit(sim_r, t), _residual_fit(null_r, t)
    opt = AttributionOptions()
    effects = {"stub_offset": StubOffset(), "stub_nothing": StubNothing()}
    from imugraph.diagnose.run import null_fold_gap
    floor = null_fold_gap(null, sim, real.sigma, fold_masks(t, opt), G.GapOptions())
    res = attribute(real, sim, floor, effects, opt, windows={"mag": (40.0, 60.0)})
    assert res[0].name == "stub_offset" and res[0].shrink > 0.8 and res[0].penalised > opt.margin
    assert res[0].params["offset"] == pytest.approx([2.0, -1.0, 1.6], abs=0.05)
    assert verdict(res, floor, opt) == "stub_offset"
    assert [r for r in res if r.name == "stub_nothing"][0].penalised <= 0
    noise = _residual_fit(white(), t)
    res0 = attribute(noise, sim, floor, effects, opt, windows={"mag": (40.0, 60.0)})
    assert verdict(res0, floor, opt) == "none"


def test_attribution_none_on_data_from_the_model(fits):
    m_real, m_sim, m_null = fits
    opt = AttributionOptions()
    from imugraph.diagnose.run import null_fold_gap
    floor = null_fold_gap(m_null, m_sim, m_real.sigma, fold_masks(m_real.session.t, opt), G.GapOptions())
    res = attribute(m_real, m_sim, floor, {"stub_offset": StubOffset(), "stub_nothing": StubNothing()}, opt,
                    windows={"mag": (10.0, 20.0)})
    assert verdict(res, floor, opt) == "none"


# ------------------------------------------------------------------------------------ report and command
def test_run_diagnose_writes_the_contract(tmp_path, monkeypatch):
    from imugraph.commands.diagnose import run_diagnose
    from imugraph.diagnose import run as R

    s = _disturbed(12)
    path = tmp_path / "disturbed.npz"
    np.savez(path, t=s.t, gyr=s.gyr, acc=s.acc, mag=s.mag)
    monkeypatch.setattr(R, "load_effects", lambda names=None: {"stub_offset": StubOffset(),
                                                               "stub_nothing": StubNothing()})
    monkeypatch.setattr(R, "DiagnoseOptions", functools.partial(R.DiagnoseOptions, window_hints=True))
    out = tmp_path / "out"
    args = argparse.Namespace(session=str(path), out=str(out), quiet=True, data_dir=None, keyframe_hz=5.0,
                              seed=0, effects=None)
    assert run_diagnose(args) == 0
    d = json.loads((out / "diagnosis.json").read_text())
    assert set(d["gap"]) == {"gyr", "acc", "mag"}
    assert d["verdict"] in ("none", "stub_offset", "stub_nothing")
    for e in d["effects"]:
        assert {"name", "channel", "t_start", "t_end", "gap_before", "gap_after", "shrink", "params"} <= set(e)
    for loc in d["locations"]:
        assert {"channel", "t_start", "t_end", "score"} <= set(loc)
    assert any(loc["channel"] == "mag" and loc["t_start"] < 21 < loc["t_end"] for loc in d["locations"])
    assert (out / "diagnosis.md").read_text().startswith("# Diagnosis")
    for f in ("gap_over_time.png", "residuals.png"):
        assert (out / f).stat().st_size > 1000
    assert not list(out.glob("*.tmp"))


def test_real_broad_trial_fit_and_gap_above_floor():
    from imugraph.config import broad_dir
    from imugraph.io.readers import load_session

    path = broad_dir() / "32_disturbed_attached_magnet_1cm.mat"
    if not path.exists():
        pytest.skip("BROAD data not available")
    s = load_session(path)
    s = s.slice(0, int(60 * s.rate))
    real = fit_base(s)
    rng = np.random.default_rng(0)
    a = fit_simulation(simulate_from_fit(real, rng), real)
    b = fit_simulation(simulate_from_fit(real, rng), real)
    g = G.gap(real.residuals, a.residuals, real.sigma, s.rate)
    null = G.gap(b.residuals, a.residuals, real.sigma, s.rate)
    # a real recording is not the simple base model: every channel's gap is far above the noise floor
    for c in G.CHANNELS:
        assert g[c] > 5 * null[c]
