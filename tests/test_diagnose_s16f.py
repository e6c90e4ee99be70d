"""Session 16, helper F: vibration's windows on the fitted band with a narrow-band excess (V3)–(V4)
(docs/diagnose.md §S16-F)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from imugraph.diagnose.attribute import effect_support
from imugraph.diagnose.effects import vibration as vib
from imugraph.diagnose.run import DiagnoseOptions, model_switches

RATE = 285.714


def _fit_with(t, r):
    """A fit of a sensor that does not turn (gyro zero, no bias): (V6) then explains nothing."""
    sess = SimpleNamespace(t=t, rate=RATE, n=len(t), gyr=np.zeros_like(r))
    return SimpleNamespace(residuals={"acc": r, "gyr": np.zeros_like(r), "mag": np.zeros_like(r)},
                           sigma={c: np.ones(3) for c in ("gyr", "acc", "mag")}, session=sess, n=len(t),
                           b_gyr_bias=np.zeros(3))


@pytest.fixture(scope="module")
def vibration_and_knock():
    """60 s of white accelerometer residual (0.1 m/s²) with a 45 Hz vibration (0.8 m/s² on x) over 20–35 s and
    a broadband knock (1 s of 1.5 m/s² white noise, all axes) right after it at 35.5–36.5 s and alone at 48–49 s."""
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 60.0, 1.0 / RATE)
    r = 0.1 * rng.standard_normal((len(t), 3))
    on = (t >= 20.0) & (t <= 35.0)
    r[on, 0] += 0.8 * np.sin(2 * np.pi * 45.0 * t[on])
    for a in (35.5, 48.0):
        k = (t >= a) & (t <= a + 1.0)
        r[k] += 1.5 * rng.standard_normal((int(k.sum()), 3))
    return _fit_with(t, r), (20.0, 35.0)


def test_motion_band_windows_merge_the_knock(vibration_and_knock):
    """The failure mode of (V2) alone: the knock next to the vibration is merged into its window."""
    fit, (a, b) = vibration_and_knock
    wins = vib.EFFECT.find_windows(fit)
    assert any(w[1] > 36.0 and w[0] < 21.0 for w in wins), wins


def test_band_windows_keep_the_vibration_alone(vibration_and_knock):
    """(V3)–(V4): on the band around 45 Hz the window is the vibration's (edges within 0.5 s), the knocks —
    broadband, a few per cent of their power in the band — are not windows."""
    fit, (a, b) = vibration_and_knock
    wins = vib.band_windows(fit, 43.0, 47.0)
    assert len(wins) == 1, wins
    assert abs(wins[0][0] - a) < 0.5 and abs(wins[0][1] - b) < 0.5, wins


def test_option_fit_uses_band_windows(vibration_and_knock, monkeypatch):
    """With the option the fitted effect reports the vibration's window and f₀ near 45 Hz, and its support
    (A3) is that window with the usual 1 s pad, the knock left out; without it, the (V2) window as before."""
    fit, (a, b) = vibration_and_knock
    monkeypatch.setattr(vib, "BAND_WINDOWS", True)
    corr = vib.EFFECT.fit(fit, np.ones(fit.n, bool))
    assert abs(corr.t_start - a) < 0.5 and abs(corr.t_end - b) < 0.5
    assert abs(corr.params["freq_hz"] - 45.0) < 2.0
    sup = effect_support(corr, fit.session.t)
    assert abs(sup.sum() / RATE - (corr.t_end - corr.t_start + 2.0)) < 0.1
    assert not sup[(fit.session.t > 36.6) & (fit.session.t < 36.9)].any()
    monkeypatch.setattr(vib, "BAND_WINDOWS", False)
    old = vib.EFFECT.fit(fit, np.ones(fit.n, bool))
    assert "support" not in old.deltas
    assert old.t_end > 36.0                                   # the merged window of (V2)


def test_option_switch_is_scoped():
    """DiagnoseOptions.vibration_band_windows sets the module flag for the diagnosis only; default on (S16)."""
    assert vib.BAND_WINDOWS is True
    with model_switches(DiagnoseOptions(vibration_band_windows=False)):
        assert vib.BAND_WINDOWS is False
    assert vib.BAND_WINDOWS is True
    with model_switches(DiagnoseOptions()):
        assert vib.BAND_WINDOWS is True
