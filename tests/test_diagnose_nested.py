"""S20-W: time_offset's shifted prediction (T13), the whitening Jacobian (L3) and the nested test (V'')."""

from types import SimpleNamespace

import numpy as np
import pytest

from imugraph.diagnose import attribute, nested
from imugraph.diagnose.effects import time_offset
from imugraph.diagnose.effects.linear_acceleration import LinearAccelerationCorrection
from imugraph.diagnose.run import DiagnoseOptions, model_switches


def _fake_fit(t, acc, pred):
    """The parts of a Fit that TimeOffsetCorrection.raw_residuals reads, for an acc delay."""
    session = SimpleNamespace(t=t, acc=acc, gyr=np.zeros_like(acc), mag=np.zeros_like(acc), rate=1 / (t[1] - t[0]))
    res = {"acc": acc - pred, "gyr": np.zeros_like(acc), "mag": np.zeros_like(acc)}
    return SimpleNamespace(session=session, residuals=res, predicted=lambda: {"acc": pred},
                           residuals_with=lambda acc: {**res, "acc": acc - pred})


def _corr(tau):
    return time_offset.TimeOffsetCorrection("time_offset", {"channel": "acc", "tau_s": tau}, 2, channel="acc")


def test_shifted_data_smooths_white_noise_shifted_prediction_does_not(monkeypatch):
    rng = np.random.default_rng(1)
    t = np.arange(20000) * 0.01
    pred = np.zeros((t.size, 3))
    acc = rng.standard_normal((t.size, 3))             # no delay at all: white noise of σ = 1
    fit = _fake_fit(t, acc, pred)
    monkeypatch.setattr(time_offset, "SHIFT_PREDICTION", False)
    r_old = _corr(0.005).raw_residuals(fit)["acc"][10:-10]                 # τ = ½ sample
    monkeypatch.setattr(time_offset, "SHIFT_PREDICTION", True)
    r_new = _corr(0.005).raw_residuals(fit)["acc"][10:-10]
    # linear interpolation at φ = ½ averages two samples: variance (1−φ)² + φ² = ½ (the artefact, §S20-W)
    assert np.var(r_old) == pytest.approx(0.5, rel=0.05)
    assert np.var(r_new) == pytest.approx(1.0, rel=0.05)


def test_shifted_prediction_removes_a_true_delay(monkeypatch):
    rng = np.random.default_rng(2)
    t = np.arange(5000) * 0.01
    h = np.stack([np.sin(2 * np.pi * 0.7 * t), np.cos(2 * np.pi * 0.4 * t), np.sin(2 * np.pi * 1.1 * t)], axis=1)
    tau = 0.043                                                            # 4.3 samples
    acc = np.stack([np.sin(2 * np.pi * 0.7 * (t - tau)), np.cos(2 * np.pi * 0.4 * (t - tau)),
                    np.sin(2 * np.pi * 1.1 * (t - tau))], axis=1) + 0.01 * rng.standard_normal((t.size, 3))
    monkeypatch.setattr(time_offset, "SHIFT_PREDICTION", True)
    r = _corr(tau).raw_residuals(_fake_fit(t, acc, h))["acc"][20:-20]
    assert np.std(r) == pytest.approx(0.01, rel=0.1)                       # only the measurement noise is left


def _circulant_logdet(g_rfft: np.ndarray, n: int) -> float:
    """ln|det| of the n×n zero-phase filter with real gain g on rfftfreq(n), built as an explicit matrix."""
    eye = np.eye(n)
    m = np.fft.irfft(np.fft.rfft(eye, axis=0) * g_rfft[:, None], n=n, axis=0)
    return float(np.linalg.slogdet(m)[1])


@pytest.mark.parametrize("n", [64, 65])
def test_log_det_matches_explicit_matrix(n):
    f = np.fft.rfftfreq(n)
    g = np.stack([1.0 / np.sqrt(1.0 + 4.0 / (1.0 + (f / 0.1) ** 4)),
                  np.full(f.size, 0.5), np.ones(f.size)], axis=1)
    want = sum(_circulant_logdet(g[:, a], n) for a in range(3)) / n
    assert nested._mean_log_gain(g, n) == pytest.approx(want, rel=1e-9, abs=1e-12)
    assert nested._mean_log_gain(np.ones((f.size, 3)), n) == 0.0
    corr = LinearAccelerationCorrection("linear_acceleration", {}, 4, deltas={"gain": lambda m, r: g})
    assert corr.log_det_per_sample(n, 100.0)["acc"] == pytest.approx(want, rel=1e-9)
    assert nested._mean_log_gain(np.full((f.size, 3), 0.5), n) == pytest.approx(3 * np.log(0.5))


def test_add_fold_charges_the_extended_model_its_jacobian():
    rng = np.random.default_rng(3)
    r = {c: rng.standard_normal((400, 3)) for c in ("gyr", "acc", "mag")}
    test = np.zeros(400, bool)
    test[::5] = True
    plain, charged = nested.GainAccumulator(), nested.GainAccumulator()
    plain.add(r, r, ~test, test)
    charged.add(r, r, ~test, test, j_ext={"acc": np.full(400, -0.2)})
    assert plain.result(0)[1]["acc"] == pytest.approx(0.0)
    assert charged.result(0)[1]["acc"] == pytest.approx(-0.2)              # same residuals, filter paid for


def _res(name, ch, pen, ll, route="log_score", rel=True):
    return SimpleNamespace(name=name, channel=ch, penalised=pen, loglik_gain=ll, support_fraction=1.0,
                           params={"significance": route} if route else {}, decisive=False, significant=True,
                           relevant=rel, explained_by=None, error=None, n_params=1)


def test_by_log_score_only():
    assert nested.by_log_score_only(_res("time_offset", "acc", -0.01, 0.18), 0.25)
    assert not nested.by_log_score_only(_res("time_offset", "acc", 0.30, 0.18), 0.25)     # (A2) on its own
    assert not nested.by_log_score_only(_res("gyro_scale", "gyr", 0.10, 0.18, route=None), 0.25)


def test_check_nested_marks_an_effect_that_does_not_beat_the_stronger_one(monkeypatch):
    e, g = _res("time_offset", "acc", -0.01, 0.18), _res("linear_acceleration", "acc", 0.24, 3.5, route=None)
    other = _res("gyro_scale", "gyr", 0.1, 9.0, route=None)
    calls = []

    def fake(real, folds, res, oth, eff, oeff, gain=(-0.1, [0.1, -0.2, 0.1])):
        calls.append(oth.name)
        return {"other": oth.name, "channel": res.channel, "nested_gain": gain[0], "nested_folds": gain[1],
                "own_gain": res.loglik_gain, "other_gain": oth.loglik_gain}

    monkeypatch.setattr(nested, "nested_gain", fake)
    effects = {"time_offset": 0, "linear_acceleration": 0, "gyro_scale": 0}
    nested.check_nested([g, e, other], None, [], effects, 0.25)
    assert calls == ["linear_acceleration"]                               # same channel, larger log score only
    assert e.explained_by["other"] == "linear_acceleration"


def test_options_switch_the_module_flags_and_restore_them():
    old = (nested.NESTED_CHECK, time_offset.SHIFT_PREDICTION, attribute.WHITENING_JACOBIAN)
    with model_switches(DiagnoseOptions(nested_check=True, shift_prediction=True, whitening_jacobian=True)):
        assert nested.NESTED_CHECK and time_offset.SHIFT_PREDICTION and attribute.WHITENING_JACOBIAN
    assert (nested.NESTED_CHECK, time_offset.SHIFT_PREDICTION, attribute.WHITENING_JACOBIAN) == old == (False,) * 3
