"""Session 20, helper V20: vibration's relevance against the measured angular motion (V6) and time_offset's
relevance with its folds' uncertainty (T12) (docs/diagnose.md §S20-V)."""

from __future__ import annotations

import argparse
from types import SimpleNamespace

import numpy as np
import pytest

from imugraph.diagnose.effects import time_offset as tof
from imugraph.diagnose.effects import vibration as vib
from imugraph.diagnose.run import DiagnoseOptions, model_switches

RATE = 285.714


def _band_noise(rng, n, f_lo, f_hi):
    """(n, 3) white noise band-passed to f_lo … f_hi Hz (FFT mask), unit RMS per axis."""
    x = rng.standard_normal((n, 3))
    f = np.fft.rfftfreq(n, 1.0 / RATE)
    y = np.fft.irfft(np.fft.rfft(x, axis=0) * ((f >= f_lo) & (f <= f_hi))[:, None], n=n, axis=0)
    return y / np.sqrt(np.mean(y**2, axis=0))


@pytest.fixture(scope="module")
def hand_and_motor():
    """60 s; over 20–40 s the body turns with a fast tremor-like component of 18–26 Hz in its rate (the gyro
    sees it). `hand`: the accelerometer residual is that rotation's tangential acceleration α × r at
    r = 0.05 m (a sensor half a hand's lever arm from the pivot), 1 m/s² RMS per axis; `motor`: the same
    rotation with the accelerometer's motion part left out and a 45 Hz, 1.5 m/s² vibration on x instead —
    in the accelerometer only. Both on 0.05 m/s² white noise."""
    rng = np.random.default_rng(20)
    t = np.arange(0.0, 60.0, 1.0 / RATE)
    n = len(t)
    on = (t >= 20.0) & (t <= 40.0)
    w_hf = _band_noise(rng, n, 18.0, 26.0) * on[:, None]
    alpha = np.gradient(w_hf, t, axis=0)
    w_hf *= 1.0 / (0.05 * np.sqrt(np.mean(alpha[on] ** 2)))      # α × r at r = 0.05 m: 1 m/s² RMS per axis
    alpha = np.gradient(w_hf, t, axis=0)
    gyr = w_hf + np.array([0.5, -0.3, 0.2]) * on[:, None]        # plus a slow turn during the window
    noise = 0.05 * rng.standard_normal((n, 3))
    motor = noise.copy()
    motor[on, 0] += 1.5 * np.sin(2 * np.pi * 45.0 * t[on])

    def fit_with(r_acc):
        sess = SimpleNamespace(t=t, rate=RATE, n=n, gyr=gyr)
        return SimpleNamespace(residuals={"acc": r_acc, "gyr": np.zeros_like(r_acc), "mag": np.zeros_like(r_acc)},
                               sigma={c: np.ones(3) for c in ("gyr", "acc", "mag")}, session=sess, n=n,
                               b_gyr_bias=np.zeros((n, 3)))

    return fit_with(noise + 0.05 * alpha), fit_with(motor)


def test_motion_check_drops_the_hands_own_high_frequency_content(hand_and_motor, monkeypatch):
    """The hand: a window and a band excess above the 0.3 m/s² relevance (relevant without the check), but the
    gyro's rotation at the 0.1 m lever arm explains more than it (r = 0.05 m < 0.1 m) → not relevant with it."""
    hand, _ = hand_and_motor
    monkeypatch.setattr(vib, "MOTION_CHECK", False)
    plain = vib.EFFECT.fit(hand, np.ones(hand.n, bool))
    assert plain.params["windows"], "the window of the hand's fast content is found"
    s0 = vib.EFFECT.size(plain, hand)
    assert s0["value"] >= s0["threshold"] == vib.RELEVANT_RMS and "motion_rms" not in s0
    monkeypatch.setattr(vib, "MOTION_CHECK", True)
    corr = vib.EFFECT.fit(hand, np.ones(hand.n, bool))
    s1 = vib.EFFECT.size(corr, hand)
    assert s1["value"] == pytest.approx(s0["value"])              # the fit itself is unchanged
    assert s1["motion_rms"] > s1["value"] and s1["threshold"] == s1["motion_rms"]


def test_motion_check_keeps_a_vibration_the_rotation_does_not_explain(hand_and_motor, monkeypatch):
    """The motor: the same rotation, 1.5 m/s² at 45 Hz in the accelerometer only → band RMS ≈ 1.5/√2 and the
    rotation explains ≈ nothing at 45 Hz (its content is 18–26 Hz): relevant with the check."""
    _, motor = hand_and_motor
    monkeypatch.setattr(vib, "MOTION_CHECK", True)
    corr = vib.EFFECT.fit(motor, np.ones(motor.n, bool))
    assert abs(corr.params["freq_hz"] - 45.0) < 2.0
    s = vib.EFFECT.size(corr, motor)
    assert s["value"] > 0.5 and s["motion_rms"] < 0.1 * s["value"]
    assert s["value"] >= s["threshold"] == vib.RELEVANT_RMS


def test_timing_confidence_jackknife_by_hand(monkeypatch):
    """(T12): folds 1, 2, 3 samples → SE² = (2/3)·2 = 4/3, threshold 1 + 1.645·√(4/3) = 2.8995."""
    monkeypatch.setattr(tof, "SIZE_CONFIDENCE", True)
    out = tof.EFFECT.size_bound({"value": 2.0, "threshold": 1.0, "unit": "samples"}, [1.0, 2.0, 3.0])
    assert out["se"] == pytest.approx(np.sqrt(4.0 / 3.0))
    assert out["threshold"] == pytest.approx(2.8995, abs=1e-3)
    assert out["value"] == 2.0


def test_timing_confidence_keeps_a_clear_delay_and_drops_one_at_the_threshold(monkeypatch):
    """A 4.4-sample delay found alike in every fold stays relevant; 1.2 samples whose folds spread over
    0.88–1.44 (BROAD 07's) is not shown to exceed 1 sample; off, or < 3 finite folds: unchanged."""
    monkeypatch.setattr(tof, "SIZE_CONFIDENCE", True)
    clear = tof.EFFECT.size_bound({"value": 4.44, "threshold": 1.0}, [4.34, 4.53, 4.54, 4.41, 4.45])
    assert clear["value"] >= clear["threshold"]
    edge = tof.EFFECT.size_bound({"value": 1.205, "threshold": 1.0}, [0.88, 1.34, 1.44, 1.01, 1.35])
    assert edge["value"] < edge["threshold"]
    few = {"value": 1.2, "threshold": 1.0}
    assert tof.EFFECT.size_bound(few, [1.0, float("nan"), np.nan]) == few
    monkeypatch.setattr(tof, "SIZE_CONFIDENCE", False)
    assert tof.EFFECT.size_bound(few, [0.88, 1.34, 1.44, 1.01, 1.35]) == few


def test_switches_default_on_and_scoped():
    """DiagnoseOptions / command-line flags set the module flags for one diagnosis only; default on since
    session 20."""
    from imugraph.diagnose.bench import diagnose_options, model_arguments

    assert vib.MOTION_CHECK is True and tof.SIZE_CONFIDENCE is True
    with model_switches(DiagnoseOptions(vibration_motion_check=False, timing_confidence=False)):
        assert vib.MOTION_CHECK is False and tof.SIZE_CONFIDENCE is False
    assert vib.MOTION_CHECK is True and tof.SIZE_CONFIDENCE is True
    p = argparse.ArgumentParser()
    model_arguments(p)
    o = diagnose_options(p.parse_args(["--no-vibration-motion-check", "--no-timing-confidence"]))
    assert o.vibration_motion_check is False and o.timing_confidence is False
    o = diagnose_options(p.parse_args([]))
    assert o.vibration_motion_check is None and o.timing_confidence is None


@pytest.fixture(scope="module")
def delayed_acc():
    """A simulated session (100 Hz, 40 s) whose accelerometer is late by 30 ms (3 samples), fitted, with its two
    simulations (as tests/test_diagnose_s17h.py)."""
    from imugraph.diagnose.bench import simulated_session
    from imugraph.diagnose.effects.base import replace_session, shift_signal
    from imugraph.diagnose.fit import fit_base, fit_simulation, simulate_from_fit

    s = simulated_session(11, 40.0, 100.0)
    real = fit_base(replace_session(s, acc=shift_signal(s.t, s.acc, 0.03)))
    rng = np.random.default_rng(0)
    sim = fit_simulation(simulate_from_fit(real, rng, name="A"), real)
    null = fit_simulation(simulate_from_fit(real, rng, name="B"), real)
    return real, sim, null


def test_attribution_applies_the_fold_bound_and_keeps_a_clear_delay(delayed_acc, monkeypatch):
    """evaluate_effect hands the folds' sizes to `size_bound`: with (T12) the size carries the folds' SE and
    the threshold 1 + 1.645 SE; a 3-sample delay stays relevant. Off: the plain 1-sample threshold."""
    from imugraph.diagnose.attribute import AttributionOptions, evaluate_effect, fold_masks
    from imugraph.diagnose.run import null_fold_gap

    real, sim, null = delayed_acc
    opt = AttributionOptions()
    folds = fold_masks(real.session.t, opt)
    floor = null_fold_gap(null, sim, real.sigma, folds, DiagnoseOptions().gap)
    monkeypatch.setattr(tof, "SIZE_CONFIDENCE", True)
    on = evaluate_effect(tof.EFFECT, real, sim, floor, folds, opt, null=null)
    taus = np.asarray(on.fold_sizes, float)
    se = np.sqrt((len(taus) - 1) / len(taus) * np.sum((taus - taus.mean()) ** 2))
    assert on.size["se"] == pytest.approx(se) and on.size["threshold"] == pytest.approx(1.0 + 1.645 * se)
    assert on.channel == "acc" and on.relevant
    monkeypatch.setattr(tof, "SIZE_CONFIDENCE", False)
    off = evaluate_effect(tof.EFFECT, real, sim, floor, folds, opt, null=null)
    assert "se" not in off.size and off.size["threshold"] == 1.0
