"""The diagnosis' speed-ups give the same numbers as the routines they replace or cache (issue 5):
sort-based quantiles vs numpy.quantile, the rotation-only preintegration vs the calibration's, the Jacobian
column cache and the base noise-level cache vs fresh computations, and the alternation's convergence test."""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.diagnose.bench import simulated_session
from imugraph.diagnose.effects import EFFECTS
from imugraph.diagnose.effects import base as effects_base
from imugraph.diagnose.effects import trajectory
from imugraph.diagnose.fit import fit_base
from imugraph.diagnose.gap import quantiles
from imugraph.diagnose.refit import CONVERGED, _change, refit_effect
from imugraph.factors.gyro import keyframe_layout, preintegrate


@pytest.fixture(scope="module")
def clean():
    s = simulated_session(4, 30.0, 100.0)
    return s, fit_base(s)


@pytest.mark.parametrize("n", [1, 2, 10, 11, 257, 4001])
def test_quantiles_are_numpys_linear_quantiles(n):
    rng = np.random.default_rng(n)
    x = rng.standard_t(3, size=(n, 3))
    x[: n // 3, 1] = 0.5                                   # ties
    u = (np.arange(256) + 0.5) / 256
    want = np.stack([np.quantile(x[:, a], u) for a in range(3)], axis=1)
    np.testing.assert_array_equal(quantiles(x, u), want)


@pytest.mark.parametrize("per_sample", [False, True])
def test_rotation_only_preintegration_is_the_calibrations(per_sample):
    rng = np.random.default_rng(3)
    n = 1000                                               # 1000 = 17·58 + 14: a short last interval
    gyr = rng.standard_normal((n, 3))
    dt = np.full(n, 0.01) + rng.uniform(0, 1e-3, n)
    kf, skf = keyframe_layout(n, 17)
    bias = 0.02 * rng.standard_normal((n, 3) if per_sample else 3)
    want = preintegrate(gyr, dt, kf, skf, bias, np.full(3, 0.01))
    got = trajectory._rotations_only(gyr, dt, kf, skf, bias)
    np.testing.assert_allclose(got.kRb, want.kRb, rtol=0, atol=1e-14)
    np.testing.assert_allclose(got.delta_R, want.delta_R, rtol=0, atol=1e-14)


@pytest.mark.parametrize("name", ["gyro_scale", "gyro_bias_drift"])
def test_cached_columns_give_the_fresh_fit(clean, name):
    """Two folds fitted with the column cache warm equal the same folds fitted with it cleared."""
    s, f = clean
    s2, _ = EFFECTS[name].inject(s, np.random.default_rng(5))
    g = fit_base(s2)
    folds = [np.arange(g.n) % 3 != k for k in range(2)]
    warm = [EFFECTS[name].fit(g, m) for m in folds]        # the second fold reuses the first's columns
    fresh = []
    for m in folds:
        trajectory._COLUMN_CACHE.clear()
        trajectory._EXACT_CACHE.clear()
        fresh.append(EFFECTS[name].fit(g, m))
    for a, b in zip(warm, fresh):
        for k in a.params:
            np.testing.assert_array_equal(np.asarray(a.params[k]), np.asarray(b.params[k]))


def test_base_rms_is_huber_rms_and_keyed_by_the_training_mask(clean):
    _, f = clean
    for m in (np.arange(f.n) % 2 == 0, np.arange(f.n) % 2 == 1):
        for c in ("acc", "mag"):
            np.testing.assert_array_equal(effects_base.base_rms(f, c, m),
                                          effects_base.huber_rms(f.residuals[c][m], f.sigma[c]))


def test_change_known_answers(clean):
    s, _ = clean
    corr = {"acc": s.acc + 1.0}
    assert _change(corr, corr, s) == 0.0
    assert _change({"acc": s.acc + 1.1}, corr, s) == pytest.approx(0.1 / 1.1)
    assert _change({"acc": s.acc + 1.0, "mag": s.mag + 1.0}, corr, s) == np.inf    # a new channel


class _Fixed:
    """A stub effect whose correction is the same constant accelerometer offset in every round."""

    name, channel, windowed = "stub", "acc", False

    def __init__(self, step):
        self.step, self.calls = step, 0

    def fit(self, fit, train, window=None):
        self.calls += 1
        shift = 0.1 * (1.0 + self.step * self.calls)
        return type("C", (), {"params": {"shift": shift}, "t_start": None, "t_end": None,
                              "corrected": lambda _self, view: {"acc": view.session.acc + shift}})()


@pytest.mark.parametrize("step, n_fits", [(0.0, 1), (0.5, 3)])
def test_alternation_stops_when_the_correction_stops_changing(clean, monkeypatch, step, n_fits):
    """Same correction in round 2 as in round 1 (relative change 0 < CONVERGED): one base refit, not 3;
    a correction still changing by ~30 % per round: every round refits."""
    import imugraph.diagnose.refit as refit

    _, f = clean
    calls = []
    monkeypatch.setattr(refit, "fit_simulation", lambda sess, start: calls.append(1) or start)
    monkeypatch.setattr(refit, "on_session", lambda fit, session: fit)
    _, info = refit.refit_effect(_Fixed(step), f, rounds=3)
    assert len(calls) == n_fits
    assert bool(info.get("converged")) == (n_fits < 3)
    assert CONVERGED < 0.1
