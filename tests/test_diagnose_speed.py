"""The diagnosis' speed-ups give the same numbers as the routines they replace or cache (issue 5):
sort-based quantiles vs numpy.quantile, the rotation-only preintegration vs the calibration's, the Jacobian
column cache and the base noise-level cache vs fresh computations, the alternation's convergence test, and the
refit skip bound (a localised verdict found, refits of effects that cannot be localised cannot change it)."""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.diagnose.bench import simulated_session
from imugraph.diagnose.effects import EFFECTS
from imugraph.diagnose.effects import base as effects_base
from imugraph.diagnose.effects import trajectory
from imugraph.diagnose.fit import fit_base
from imugraph.diagnose.gap import quantiles
from imugraph.diagnose.refit import CONVERGED, _change
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
    monkeypatch.setattr(refit, "fit_simulation", lambda sess, start, *a, **kw: calls.append(1) or start)
    monkeypatch.setattr(refit, "on_session", lambda fit, session: fit)
    _, info = refit.refit_effect(_Fixed(step), f, rounds=3)
    assert len(calls) == n_fits
    assert bool(info.get("converged")) == (n_fits < 3)
    assert CONVERGED < 0.1


def _res(name, channel, penalised, frac, value=2.0, stage="refit", raw_before=1.0, decisive=False):
    from imugraph.diagnose.attribute import EffectResult

    return EffectResult(name, channel, 0.9, 0.1, 0.9, penalised, 3, raw_before=raw_before, floor=0.1,
                        size={"value": value, "threshold": 1.0}, stage=stage, support_fraction=frac,
                        decisive=decisive)


def test_may_be_localised_and_refit_order():
    """Windowed effects, a screening support and conclusive evidence may be localised; the library's
    global effects not. refit_order puts those first and keeps the candidates' order otherwise."""
    from imugraph.diagnose.refit import may_be_localised, refit_order

    glob = _res("x", "acc", 0.5, 1.0, stage="screen")
    expect = {"magnetic_disturbance": True, "vibration": True, "saturation": False, "linear_acceleration": False,
              "gyro_scale": False, "gyro_bias_drift": False, "time_offset": False, "accelerometer_bias": False}
    for name, want in expect.items():
        assert may_be_localised(EFFECTS[name], glob) is want, name
    assert may_be_localised(EFFECTS["saturation"], _res("s", "gyr", 0.0, 0.02, stage="screen"))
    assert may_be_localised(EFFECTS["saturation"], _res("s", "gyr", 0.0, 1.0, stage="screen", decisive=True))
    names = ["linear_acceleration", "gyro_scale", "magnetic_disturbance", "accelerometer_bias", "vibration"]
    screened = {n: glob for n in names}
    assert refit_order(names, screened, EFFECTS) == ["magnetic_disturbance", "vibration", "linear_acceleration",
                                                     "gyro_scale", "accelerometer_bias"]


def test_skipping_global_refits_after_a_local_verdict_never_changes_the_verdict():
    """The bound of refit.verdict_is_local against attribute.verdict (V): once a refitted localised
    effect is significant and relevant, ANY result of the global effects (random scores, sizes,
    significance, their screening or refit numbers) gives the same verdict. And it is not vacuous: a
    local effect that is not relevant, not significant, or not localised does not settle the verdict."""
    from imugraph.diagnose.attribute import AttributionOptions, _rank, verdict
    from imugraph.diagnose.refit import verdict_is_local

    opt, floor = AttributionOptions(), {"gyr": 0.1, "acc": 0.1, "mag": 0.1}
    local = _res("magnetic_disturbance", "mag", 0.4, 0.3)
    assert verdict_is_local([local], floor, opt)
    assert not verdict_is_local([_res("m", "mag", 0.4, 0.3, value=0.5)], floor, opt)        # not relevant
    assert not verdict_is_local([_res("m", "mag", 0.1, 0.3)], floor, opt)                   # not significant
    assert not verdict_is_local([_res("m", "mag", 0.4, 0.7)], floor, opt)                   # not localised
    assert not verdict_is_local([_res("m", "mag", 0.4, 0.3, stage="screen")], floor, opt)   # not refitted
    rng = np.random.default_rng(0)
    for _ in range(200):
        globs = [_res(n, c, float(rng.uniform(-1, 1.2)), 1.0, value=float(rng.uniform(0, 3)),
                      raw_before=float(rng.uniform(0, 2)), decisive=bool(rng.random() < 0.1))
                 for n, c in (("linear_acceleration", "acc"), ("gyro_scale", "gyr"), ("time_offset", "mag"))]
        other = _res("vibration", "acc", float(rng.uniform(-1, 1)), 0.2, value=float(rng.uniform(0, 3)))
        assert verdict(_rank([local, other] + globs), floor, opt) in ("magnetic_disturbance", "vibration")
        screened = [_res(g.name, g.channel, float(rng.uniform(-1, 1.2)), 1.0, stage="screen") for g in globs]
        assert verdict(_rank([local, other] + globs), floor, opt) == verdict(_rank([local, other] + screened),
                                                                            floor, opt)
