"""time_offset, issue 5 S14-A (docs/diagnose.md §4 S14-A): the magnetometer's sub-sample remainder is the
base model's (T5), the gyro-referenced delay is used only where rotation is most of the channel's change
(T7), and an effect may ask to be judged by the held-out log score's sign test (T6, attribute.significant).
Known answers: pure rotation against rotation plus a hand's linear acceleration written out here; a
sub-sample field shift alone; EffectResults built by hand."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from imugraph.diagnose.attribute import AttributionOptions, significant
from imugraph.diagnose.bench import simulated_session
from imugraph.diagnose.effects import time_offset as to
from imugraph.diagnose.effects.base import replace_session, shift_signal
from imugraph.diagnose.fit import fit_base
from imugraph.diagnose.result import EffectResult

RATE = 100.0


@pytest.fixture(scope="module")
def sim():
    return simulated_session(11, 40.0, RATE)


def _hand_acceleration(n: int, rate: float, rms: float, seed: int = 3) -> np.ndarray:
    """(n, 3) smooth random linear acceleration (white noise through a 0.1 s moving mean), RMS `rms` per axis."""
    rng = np.random.default_rng(seed)
    k = int(0.1 * rate)
    x = np.stack([np.convolve(rng.standard_normal(n + k), np.ones(k) / k, mode="valid")[:n] for _ in range(3)], 1)
    return rms * x / np.sqrt(np.mean(x * x, axis=0))


def test_base_remainder_is_half_a_sample():
    assert to.base_remainder(0.005, RATE) and to.base_remainder(-0.004, RATE)
    assert not to.base_remainder(0.0051, RATE) and not to.base_remainder(-0.006, RATE)
    assert to.base_remainder(0.0017, 285.714) and not to.base_remainder(0.0018, 285.714)


def test_rotation_explains_gravity_but_not_a_hands_linear_acceleration(sim):
    """(T7): the accelerometer of a simulation is gravity seen from the turning body (E ≈ 1); add a hand's
    linear acceleration several times the rotation's change of gravity and E falls below ½."""
    w = sim.gyr
    e_clean = to.rotation_explained(sim.t, sim.acc, w, 0.0)
    assert e_clean > 0.9
    acc = sim.acc + _hand_acceleration(sim.n, sim.rate, 5.0)
    assert to.rotation_explained(sim.t, acc, w, 0.0) < 0.5
    hidden = acc.copy()
    hidden[: sim.n // 2] = np.nan                      # held-out rows are left out, not a failure
    assert np.isfinite(to.rotation_explained(sim.t, hidden, w, 0.0))


def test_rotation_check_drops_the_accelerometer_delay_of_a_moving_hand(sim, monkeypatch):
    """gyro_referenced_delays on a stub fit: with (T7) an accelerometer dominated by linear acceleration
    gives no acc/gyr candidate, the field's stays; without linear acceleration its 30 ms delay is found."""
    def stub(acc):
        s = replace_session(sim, acc=acc)
        return SimpleNamespace(session=s, b_gyr_bias=np.zeros(3),
                               calibration=SimpleNamespace(D=np.eye(3), o=np.zeros(3)))

    monkeypatch.setattr(to, "ROTATION_CHECK", True)
    delayed = shift_signal(sim.t, sim.acc, 0.03)
    ref = to.gyro_referenced_delays(stub(delayed), np.ones(sim.n, bool))
    assert ref["acc"] == pytest.approx(0.03, abs=0.004) and ref["gyr"] == -ref["acc"]
    noisy = delayed + _hand_acceleration(sim.n, sim.rate, 5.0)
    ref = to.gyro_referenced_delays(stub(noisy), np.ones(sim.n, bool))
    assert "acc" not in ref and "gyr" not in ref and "mag" in ref


def test_a_sub_sample_field_shift_is_not_a_candidate(sim, monkeypatch):
    """(T5): a field shifted by 0.4 sample (within the whole-sample alignment's remainder) is what the
    magnetometer candidate takes without (T5); with it the fit reports another channel (or a shift beyond
    ½ sample)."""
    s = replace_session(sim, mag=shift_signal(sim.t, sim.mag, 0.4 / RATE))
    fit = fit_base(s)
    train = np.ones(fit.n, bool)
    monkeypatch.setattr(to, "MAG_REMAINDER_OUT", False)
    before = to.EFFECT.fit(fit, train)
    monkeypatch.setattr(to, "MAG_REMAINDER_OUT", True)
    after = to.EFFECT.fit(fit, train)
    assert before.channel == "mag" and to.base_remainder(before.params["tau_s"], RATE)
    assert after.channel != "mag" or not to.base_remainder(after.params["tau_s"], RATE)


def _result(penalised: float, folds: list, params: dict) -> EffectResult:
    gain = float(np.mean(folds))
    return EffectResult("time_offset", "acc", 0.6, 0.59, 0.02, penalised, 2, params=params, raw_before=0.6,
                        floor=0.02, loglik_gain=gain, loglik_folds=list(folds))


def test_log_score_significance_is_asked_for_by_the_fit():
    """(T6): an effect whose params ask for it is significant by the sign test (A4'') although its (A2) is
    below the margin; one negative fold, or no request, and it is not."""
    opt = AttributionOptions()
    ask = {"tau_s": -0.02, "significance": "log_score"}
    assert significant(_result(-0.01, [0.24, 0.34, 0.36, 0.23, 0.28], ask), {}, opt)
    assert not significant(_result(-0.01, [0.24, 0.34, -0.01, 0.23, 0.28], ask), {}, opt)
    assert not significant(_result(-0.01, [0.24, 0.34, 0.36, 0.23, 0.28], {"tau_s": -0.02}), {}, opt)
    assert significant(_result(0.30, [0.24, -0.1, 0.36, 0.23, 0.28], {"tau_s": -0.02}), {}, opt)   # (A2)
