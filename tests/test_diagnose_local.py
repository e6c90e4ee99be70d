"""Localised effects: support-restricted scoring (attribution (A3)), the verdict order (V), the vibration
detector's motion band (V2), the saturation injection and its rail test (C2)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from imugraph.diagnose import gap as G
from imugraph.diagnose.attribute import (AttributionOptions, EffectResult, attribute, effect_support,
                                         fold_masks, null_gaps, verdict)
from imugraph.diagnose.effects import EFFECTS
from imugraph.diagnose.effects.vibration import MOTION_BAND_HZ, above_motion_band
from imugraph.io.session import Session


def _fit(res: dict, t: np.ndarray):
    sess = SimpleNamespace(t=t, rate=float(1 / np.median(np.diff(t))), n=len(t))
    return SimpleNamespace(residuals=res, sigma={c: np.ones(3) for c in G.CHANNELS}, session=sess, n=len(t))


class _Corr:
    def __init__(self, name, res, n_params, params, window=(None, None)):
        self.name, self._res, self.n_params, self.params = name, res, n_params, params
        self.t_start, self.t_end = window
        self.deltas = {}

    def residuals(self, fit):
        return self._res

    raw_residuals = residuals          # no noise re-estimation in a stub: raw and rescaled are the same


class WindowOffset:
    """Stub windowed effect: removes the mean magnetometer residual inside a known window (training only)."""

    name, channel, windowed = "window_offset", "mag", True

    def fit(self, fit, train, window=None):
        t = fit.session.t
        inside = (t >= 40.0) & (t <= 60.0)
        r = fit.residuals["mag"]
        off = np.nanmean(r[inside & train], axis=0) - np.nanmean(r[~inside & train], axis=0)
        res = {c: fit.residuals[c].copy() for c in G.CHANNELS}
        res["mag"][inside] -= off
        return _Corr(self.name, res, 3, {"windows": [{"t_start": 40.0, "t_end": 60.0}]}, (40.0, 60.0))


def _coloured(rng, n, scale):
    """Slowly varying (coloured) misfit everywhere: what a real recording has on top of the model."""
    e = rng.standard_normal((n, 3))
    x = np.zeros((n, 3))
    for i in range(1, n):                                       # AR(1), correlation time 0.2 s at 100 Hz
        x[i] = 0.95 * x[i - 1] + e[i]
    return scale * x / np.std(x)


def test_effect_support_windows_padded_and_explicit():
    t = np.arange(0, 20, 0.01)
    c = _Corr("x", {}, 1, {"windows": [{"t_start": 5.0, "t_end": 8.0}]})
    m = effect_support(c, t)
    assert m[(t >= 4.0) & (t <= 9.0)].all() and not m[(t < 3.99) | (t > 9.01)].any()   # ± SUPPORT_PAD_S = 1 s
    c.deltas["support"] = t < 2.0
    assert np.array_equal(effect_support(c, t), t < 2.0)
    assert effect_support(_Corr("y", {}, 1, {"tau_s": 0.01}), t) is None                # global effect


def test_localised_scoring_sees_the_window_through_a_global_misfit():
    """Real residuals = white noise + a coloured misfit everywhere (a real recording is never the model)
    + an offset in [40, 60] s. Over the whole recording the offset's removal is a small part of the gap;
    on its support, against the rest of the recording (A3), it is nearly all of the excess."""
    rng = np.random.default_rng(3)
    t = np.arange(0, 100, 0.01)
    white = lambda: {c: rng.standard_normal((len(t), 3)) for c in G.CHANNELS}   # noqa: E731
    real_r, sim_r, null_r = white(), white(), white()
    real_r["mag"] += _coloured(rng, len(t), 1.5)
    real_r["mag"][(t >= 40) & (t <= 60)] += np.array([1.5, -1.0, 1.2])
    real, sim, null = _fit(real_r, t), _fit(sim_r, t), _fit(null_r, t)
    opt = AttributionOptions(refit_top=0)
    floor = null_gaps(null, sim, real.sigma, fold_masks(t, opt))
    glob = attribute(real, sim, floor, {"w": WindowOffset()}, opt)[0]
    loc = attribute(real, sim, floor, {"w": WindowOffset()}, opt, null=null)[0]
    assert loc.support_fraction == pytest.approx(22.0 / 100.0, abs=0.01)
    assert glob.support_fraction == 1.0
    assert loc.shrink > 0.7 and loc.shrink > glob.shrink + 0.2
    # without the offset, the window is like the rest: nothing to explain there
    real_r["mag"][(t >= 40) & (t <= 60)] -= np.array([1.5, -1.0, 1.2])
    none = attribute(_fit(real_r, t), sim, floor, {"w": WindowOffset()}, opt, null=null)[0]
    assert none.penalised < opt.margin


def _res(name, pen, frac, value=1.0, raw=10.0):
    return EffectResult(name, "acc", 1.0, 1.0 - pen, pen, pen, 1, size={"value": value, "threshold": 0.5},
                        raw_before=raw, floor=1.0, support_fraction=frac)


def test_verdict_prefers_a_significant_relevant_localised_effect():
    g = _res("global", 0.8, 1.0)
    loc = _res("local", 0.4, 0.2)
    weak = _res("weak_local", 0.1, 0.2)                      # not significant (A2 < margin)
    small = _res("small_local", 0.9, 0.2, value=0.1)         # not relevant
    floor = {"gyr": 1.0, "acc": 1.0, "mag": 1.0}
    assert verdict([g, loc, weak, small], floor) == "local"
    assert verdict([g, weak, small], floor) == "global"
    assert verdict([weak, small], floor) == "none"
    assert verdict([_res("noisy", 0.9, 0.2, raw=1.5)], floor) == "none"   # raw gap < 2 × its own floor


def test_above_motion_band_keeps_vibration_removes_motion():
    rate = 285.714
    t = np.arange(0, 20, 1 / rate)
    motion = np.sin(2 * np.pi * 4.0 * t)                      # hand movement / tremor band
    vib = 0.5 * np.sin(2 * np.pi * 40.0 * t)
    x = np.stack([motion + vib, motion, vib], axis=1)
    y = above_motion_band(x, rate)
    core = slice(len(t) // 10, -len(t) // 10)
    assert np.std(y[core, 1]) < 0.01                         # 4 Hz: removed
    assert np.std(y[core, 2]) == pytest.approx(np.std(vib), rel=0.02)   # 40 Hz: kept
    assert np.allclose(y[core, 0], y[core, 2], atol=0.02)
    assert MOTION_BAND_HZ < 20.0                             # below the injection range's lowest f₀


def test_saturation_injection_clips_the_requested_fraction():
    rng = np.random.default_rng(2)
    t = np.arange(0, 30, 0.01)
    gyr = 3.0 * np.sin(2 * np.pi * 0.3 * t)[:, None] * np.array([1.0, 0.5, 0.2]) + 0.1 * rng.standard_normal((len(t), 3))
    acc = np.tile([0.0, 0.0, 9.81], (len(t), 1)) + 0.05 * rng.standard_normal((len(t), 3))
    s = Session(t=t, gyr=gyr, acc=acc, mag=np.tile([0.3, 0.0, -0.5], (len(t), 1)), name="toy")
    out, truth = EFFECTS["saturation"].inject(s, np.random.default_rng(0), strength=0.03)
    assert truth["params"]["channel"] == "gyr"              # acc never reaches 2 g: the gyro clips
    assert truth["params"]["clipped_fraction"] == pytest.approx(0.03, abs=0.002)
    assert np.nanmax(np.abs(out.gyr)) == pytest.approx(truth["params"]["level"])
    assert np.array_equal(s.gyr, gyr)                        # input untouched


def test_rail_in_separate_episodes_is_decisive():
    """(C2): a clipped sine reaches its rail once per period (separate runs) — decisive and significant
    whatever its gap shrink; a smooth unclipped signal has no rail."""
    from imugraph.diagnose.attribute import significant
    from imugraph.diagnose.effects.saturation import find_rails, separate_runs

    t = np.arange(0, 10, 0.01)
    y = np.sin(2 * np.pi * 0.5 * t)[:, None] * np.ones((1, 3))
    clipped = np.clip(y, -0.8, 0.8)
    assert separate_runs(clipped[:, 0], 0.8, t) == 5                 # one episode per period (0.5 Hz, 10 s)
    assert find_rails(y + 1e-3 * np.random.default_rng(0).standard_normal(y.shape), np.ones(len(t), bool)) == []
    r = _res("saturation", -0.5, 0.2)
    floor = {"gyr": 1.0, "acc": 1.0, "mag": 1.0}
    assert not significant(r, floor)
    r.decisive = True
    assert significant(r, floor) and verdict([_res("global", 0.8, 1.0), r], floor) == "saturation"
