"""Effect library of the diagnosis (imugraph.diagnose.effects): injection round trips, and for each effect
inject → fit on training blocks → parameters recovered and held-out residual reduced; on a clean
simulation the correction changes the held-out residual by ≈ 0."""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.diagnose.bench import simulated_session
from imugraph.diagnose.effects import EFFECTS
from imugraph.diagnose.effects.base import (detect_windows, envelope, gyro_refit, interval_mean, refine_edge,
                                             shift_signal)
from imugraph.diagnose.effects.saturation import find_rails, reconstruct_peaks
from imugraph.diagnose.harness import hide_label, interval_iou

fit_mod = pytest.importorskip("imugraph.diagnose.fit")


@pytest.fixture(scope="module")
def clean():
    s = simulated_session(3, 40.0, 100.0)
    return s, fit_mod.fit_base(s)


def held_out(t):
    block = np.floor((t - t[0]) / 2.0).astype(int)        # interleaved 2 s blocks, fold 1 of 5
    return block % 5 == 1


def rms(x, m):
    return float(np.sqrt(np.nanmean(x[m] ** 2)))


def test_registry_names_and_interface():
    assert set(EFFECTS) == {"magnetic_disturbance", "linear_acceleration", "gyro_bias_drift", "time_offset",
                            "gyro_scale", "saturation", "accelerometer_bias", "vibration", "timestamp_jitter"}
    for name, e in EFFECTS.items():
        assert e.name == name and e.channel in ("gyr", "acc", "mag") and e.ranges


@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_inject_does_not_modify_input_and_reports_truth(name):
    s = simulated_session(1, 20.0, 100.0)
    before = [a.copy() for a in (s.gyr, s.acc, s.mag, s.t)]
    s2, truth = EFFECTS[name].inject(s, np.random.default_rng(0))
    for a, b in zip(before, (s.gyr, s.acc, s.mag, s.t)):
        np.testing.assert_array_equal(a, b)
    assert s2.n == s.n and set(truth) >= {"params", "t_start", "t_end"}
    changed = [not np.allclose(a, b, equal_nan=True) for a, b in zip(before, (s2.gyr, s2.acc, s2.mag, s2.t))]
    # one channel changed — or, for timestamp_jitter, only the stamps (the samples are the sensor's own)
    assert changed == [False, False, False, True] if name == "timestamp_jitter" else sum(changed) == 1
    if EFFECTS[name].windowed:
        assert s.t[0] < truth["t_start"] < truth["t_end"] < s.t[-1]
    hidden = hide_label(s2, "x")
    assert name not in hidden.name and "injected" not in hidden.meta


def test_shift_signal_known_answer():
    t = np.arange(0, 2, 0.01)
    y = np.stack([np.sin(t), t, t**2], 1)
    out = shift_signal(t, y, 0.05)
    np.testing.assert_allclose(out[10:, 1], t[10:] - 0.05, atol=1e-12)          # linear: exact


def test_envelope_and_iou():
    t = np.linspace(0, 10, 1001)
    e = envelope(t, (3.0, 6.0), 1.0)
    assert e[0] == 0 and e[450] == 1 and abs(e[300] - 0.5) < 1e-9
    assert interval_iou((0, 10), (5, 15)) == pytest.approx(5 / 15)
    assert interval_iou((0, 1), None) == 0.0


def test_detect_windows_and_refine_edge():
    rng = np.random.default_rng(0)
    t = np.arange(0, 60, 0.01)
    x = rng.standard_normal((len(t), 3))
    x[2000:3500] += 5.0
    wins = detect_windows(t, np.sum(x**2, 1) / 3)
    assert len(wins) == 1
    a = refine_edge(x, wins[0][0], 200)
    b = refine_edge(x, wins[0][1] - 1, 200)
    assert abs(a - 2000) <= 3 and abs(b - 3500) <= 3


def test_rails_found_only_when_clipped():
    t = np.arange(0, 10, 0.01)
    y = np.stack([3 * np.sin(2 * t), np.cos(t), 0.1 * t], 1)
    assert find_rails(y, np.ones(len(t), bool)) == []
    yc = np.clip(y, -2.5, 2.5)
    rails = find_rails(yc, np.ones(len(t), bool))
    assert {(a, s) for a, s, _ in rails} == {(0, 1.0), (0, -1.0)}
    rec = reconstruct_peaks(t, yc, rails)
    assert np.max(np.abs(rec[:, 0] - y[:, 0])) < 0.15                              # peaks restored
    assert np.max(np.abs(rec[:, 0])) > 2.8


def test_gyro_refit_is_affine_and_zero_for_zero_change(clean):
    _, f = clean
    r0, d0 = gyro_refit(f, np.zeros((f.n, 3)))
    for c in ("gyr", "acc", "mag"):
        np.testing.assert_allclose(r0[c], f.residuals[c], equal_nan=True)
    assert np.all(d0 == 0)
    rng = np.random.default_rng(1)
    a, b = 1e-3 * rng.standard_normal((f.n, 3)), 1e-3 * rng.standard_normal((f.n, 3))
    ra, rb, rab = gyro_refit(f, a)[0], gyro_refit(f, b)[0], gyro_refit(f, a + b)[0]
    for c in ("gyr", "acc", "mag"):
        np.testing.assert_allclose(rab[c] - f.residuals[c], (ra[c] - f.residuals[c]) + (rb[c] - f.residuals[c]),
                                   atol=1e-12, equal_nan=True)
    # a constant gyro change c over an interval of length T: the keyframe mismatch moves by exactly c
    c = np.array([1e-3, -2e-3, 5e-4])
    r = gyro_refit(f, np.tile(c, (f.n, 1)))[0]
    inner = np.isfinite(r["gyr"][:, 0])
    inner[f.keyframe_samples[-1]:] = False
    np.testing.assert_allclose((r["gyr"] - f.residuals["gyr"])[inner], np.tile(c, (inner.sum(), 1)), atol=1e-9)
    m = interval_mean(f, np.tile(c, (f.n, 1)))
    np.testing.assert_allclose(m, np.tile(c, (f.n, 1)))


@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_clean_session_correction_changes_little(clean, name):
    s, f = clean
    held = held_out(s.t)
    corr = EFFECTS[name].fit(f, ~held)
    r = corr.residuals(f)
    for c in ("gyr", "acc", "mag"):
        before = rms(f.residuals[c] / f.sigma[c], held)
        after = rms(r[c] / f.sigma[c], held)
        assert abs(after - before) <= 0.1 * before, (name, c, before, after)


CASES = {   # name: (strength, channel judged, required held-out reduction of the whitened RMS before rule 3)
    "magnetic_disturbance": (15.0, "mag", None),     # larger fields bend the base fit (see report)
    "linear_acceleration": (2.0, "acc", 0.5),
    "time_offset": (0.03, None, 0.4),
    "accelerometer_bias": (0.2, "acc", 0.1),
    "vibration": (1.5, "acc", 0.5),
    "gyro_scale": (np.eye(3) + np.diag([0.02, -0.02, 0.015]), "gyr", 0.3),
}


KNOWN_WEAK = {"accelerometer_bias": "first-order refit: the base fit tilts its orientation to absorb most of a "
                                    "constant accelerometer bias, which a fixed-trajectory refit cannot undo"}


@pytest.mark.parametrize("name", sorted(CASES))
def test_injected_effect_recovered_on_held_out_time(clean, name, request):
    if name in KNOWN_WEAK:
        request.applymarker(pytest.mark.xfail(reason=KNOWN_WEAK[name], strict=False))
    s, _ = clean
    strength, channel, reduction = CASES[name]
    rng = np.random.default_rng(11)
    s2, truth = EFFECTS[name].inject(s, rng, strength=strength)
    f = fit_mod.fit_base(s2)
    held = held_out(s.t)
    corr = EFFECTS[name].fit(f, ~held)
    channel = channel or truth["params"]["channel"]
    before = rms(f.residuals[channel] / f.sigma[channel], held)
    after = rms(corr.raw_residuals(f)[channel] / f.sigma[channel], held)
    if reduction is not None:
        assert after < (1 - reduction) * before, (before, after)
    p, q = truth["params"], corr.params
    if name == "magnetic_disturbance":
        est = np.asarray(q["windows"][0]["body_offset"])
        assert np.linalg.norm(est - p["vector"]) < 0.35 * np.linalg.norm(p["vector"])
        assert interval_iou((truth["t_start"], truth["t_end"]), (corr.t_start, corr.t_end)) > 0.7
    elif name == "time_offset":
        assert q["channel"] == p["channel"] and abs(q["tau_s"] - p["tau_s"]) < 0.3 * p["tau_s"]
    elif name == "vibration":
        assert abs(q["freq_hz"] - p["freq_hz"]) < 2.0
        assert interval_iou((truth["t_start"], truth["t_end"]), (corr.t_start, corr.t_end)) > 0.8
    elif name == "gyro_scale":
        est = np.diag(np.asarray(q["M"]))
        assert np.all(np.sign(est) == np.sign(np.diag(p["M"]))) and np.all(np.abs(est) > 0.3 * np.abs(np.diag(p["M"])))
    elif name == "accelerometer_bias":
        est = np.asarray(q["bias_ms2"])
        assert est @ np.asarray(p["bias_ms2"]) > 0.5 * np.dot(p["bias_ms2"], p["bias_ms2"])


def test_saturation_rails_recovered(clean):
    s, _ = clean
    s2, truth = EFFECTS["saturation"].inject(s, np.random.default_rng(5), strength=0.02)   # 2 % of the samples beyond the rail
    f = fit_mod.fit_base(s2)
    corr = EFFECTS["saturation"].fit(f, ~held_out(s.t))
    levels = [abs(r["level"]) for r in corr.params["rails"][truth["params"]["channel"]]]
    assert levels and np.allclose(levels, truth["params"]["level"])
    assert corr.n_params == len(levels)
