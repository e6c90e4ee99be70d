"""The joint gyro estimator scored by its own held-out cost (imugraph.diagnose.effects.joint (J5),
score.OwnCostAccumulator, attribute.significant) and the model switches of DiagnoseOptions (issue 5, G7)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from imugraph.diagnose.attribute import AttributionOptions, fold_masks, significant
from imugraph.diagnose.bench import simulated_session
from imugraph.diagnose.effects import EFFECTS
from imugraph.diagnose.effects.joint import heldout_cost
from imugraph.diagnose.fit import fit_base
from imugraph.diagnose.result import EffectResult
from imugraph.diagnose.run import DiagnoseOptions, model_switches
from imugraph.diagnose.score import OwnCostAccumulator, clearly_better


def _huber_by_hand(z, k=2.0):
    """ρ on a = ‖z‖/√3: ½‖z‖² inside (= 3/2 a²), linear beyond k (3 (k a − k²/2)), row by row."""
    total = 0.0
    for row in z:
        a = float(np.sqrt(sum(v * v for v in row) / 3.0))
        total += 0.5 * sum(v * v for v in row) if a <= k else 3.0 * (k * a - 0.5 * k * k)
    return total


def test_heldout_cost_known_answer():
    """(J5) on known residuals: the held-out rows only, NaN rows of either model left out of both, the gyro
    whitened by σ_ω·√stride (per sample), acc/mag by the fit's σ."""
    fit = SimpleNamespace(sigma={"gyr": np.array([0.01, 0.01, 0.02]), "acc": np.array([0.1, 0.1, 0.1]),
                                 "mag": np.array([1.0, 2.0, 1.0])}, info={"stride": 4})
    rng = np.random.default_rng(3)
    rb = {c: rng.standard_normal((8, 3)) * s for c, s in fit.sigma.items()}
    re = {c: 0.5 * v for c, v in rb.items()}
    rb["acc"][1] = [3.0, -2.0, 4.0]                  # an outlier row (a > 2 after whitening)
    re["mag"][2] = np.nan                            # left out of both models
    test = np.array([1, 1, 1, 0, 1, 0, 1, 0], bool)
    out = heldout_cost(fit, rb, re, test)
    for c in ("gyr", "acc", "mag"):
        s = fit.sigma[c] * (2.0 if c == "gyr" else 1.0)
        rows = [i for i in range(8) if test[i] and np.all(np.isfinite(re[c][i]))]
        assert out["n"][c] == len(rows)
        assert out["base"][c] == pytest.approx(_huber_by_hand(rb[c][rows] / s))
        assert out["ext"][c] == pytest.approx(_huber_by_hand(re[c][rows] / s))


def test_own_cost_accumulator_gains_and_sign_test():
    """Per-sample gains (C_base − C_ext)/rows per channel, the fold sums and the BIC cost k ln N/(2N)."""
    acc = OwnCostAccumulator()
    acc.add_costs({"base": {"gyr": 10.0, "acc": 20.0, "mag": 5.0}, "ext": {"gyr": 8.0, "acc": 19.0, "mag": 5.0},
                   "n": {"gyr": 100, "acc": 100, "mag": 100}})
    acc.add_costs({"base": {"gyr": 10.0, "acc": 20.0, "mag": 5.0}, "ext": {"gyr": 12.0, "acc": 20.0, "mag": 5.5},
                   "n": {"gyr": 100, "acc": 100, "mag": 100}})
    gain, per, n = acc.result(0)
    assert n == 200
    assert per["gyr"] == pytest.approx(0.0) and per["acc"] == pytest.approx(0.005)
    assert per["mag"] == pytest.approx(-0.0025)
    assert gain == pytest.approx(0.0025)
    folds = acc.fold_gains(6)
    cost = 6 * np.log(200) / 400
    assert folds == pytest.approx([0.03 - cost, -0.025 - cost])
    assert not clearly_better(acc.result(6)[0], folds)               # one fold worse: not clearly better


def test_own_cost_shrink_known_answer():
    """(J6): (gain − BIC) over the base model's excess above its own noise's cost, channels without an
    excess (acc/mag: σ fitted by ML) not counted."""
    acc = OwnCostAccumulator()
    held = {"base": {"gyr": 50.0, "acc": 140.0, "mag": 160.0}, "ext": {"gyr": 40.0, "acc": 140.0, "mag": 158.0},
            "n": {"gyr": 100, "acc": 100, "mag": 100}, "e0": {"gyr": 0.1, "acc": 1.5, "mag": 1.5}}
    acc.add_costs(held)
    acc.add_costs(held)
    cost = 2 * np.log(200) / 400
    excess = (0.5 - 0.1) + 0.0 + (1.6 - 1.5)           # acc: 1.4 < 1.5, no excess
    assert acc.shrink(2) == pytest.approx((0.1 + 0.02 - cost) / excess)
    assert np.isnan(OwnCostAccumulator().shrink(2))


def _result(penalised, own_folds):
    r = EffectResult("gyro_scale", "gyr", 1.0, 0.9, 0.1, penalised, 6, raw_before=10.0,
                     size={"value": 0.01, "threshold": 0.003})
    if own_folds is not None:
        r.own_folds = list(own_folds)
        r.own_gain = float(np.mean(own_folds))
        r.own_shrink = 0.5
    return r


def test_significance_by_the_own_cost_when_the_fit_reports_one():
    """An effect whose fit reports (J5) is judged by its sign test, not by (A2); without (J5) as before."""
    null = {"gyr": 1.0, "acc": 1.0, "mag": 1.0}
    on, off = AttributionOptions(), AttributionOptions(own_score="")
    assert significant(_result(-0.5, [0.1, 0.2, 0.05, 0.1, 0.3]), null, on)
    assert not significant(_result(-0.5, [0.1, 0.2, 0.05, 0.1, 0.3]), null, off)
    assert not significant(_result(0.9, [0.1, -0.2, 0.05, 0.1, 0.3]), null, on)
    assert significant(_result(0.9, None), null, on)                  # no (J5): (A2) as before
    small = _result(0.9, [0.1, 0.2, 0.05, 0.1, 0.3])
    small.own_shrink = 0.1                                            # (J6) below the margin
    assert not significant(small, null, on)


def test_model_switches_set_and_restore_the_module_flags():
    from imugraph.diagnose import fit as fitmod
    from imugraph.diagnose.effects import joint

    before = (joint.ENABLED, fitmod.SUBSAMPLE_LAG)
    with model_switches(DiagnoseOptions(joint_gyro=True, subsample_lag=True)):
        assert joint.ENABLED and fitmod.SUBSAMPLE_LAG
    assert (joint.ENABLED, fitmod.SUBSAMPLE_LAG) == before
    with model_switches(DiagnoseOptions()):                           # None: the modules' own values
        assert (joint.ENABLED, fitmod.SUBSAMPLE_LAG) == before
    with pytest.raises(RuntimeError):
        with model_switches(DiagnoseOptions(joint_gyro=not before[0])):
            raise RuntimeError("boom")
    assert (joint.ENABLED, fitmod.SUBSAMPLE_LAG) == before


@pytest.fixture(scope="module")
def host():
    s = simulated_session(11, 20.0, 100.0)
    return s, fit_base(s)


def _own(fit, name="gyro_scale"):
    with model_switches(DiagnoseOptions(joint_gyro=True)):
        acc = OwnCostAccumulator()
        for fold in fold_masks(fit.session.t, AttributionOptions()):
            corr = EFFECTS[name].fit(fit, ~fold)
            acc.add_costs(corr.deltas["heldout"])
        n_params = corr.n_params
        return acc.result(n_params)[0], acc.fold_gains(n_params), acc.shrink(n_params)


def test_own_cost_sees_an_injected_scale_and_not_a_clean_host(host):
    """Known answer on a simulation (data from the base model): a 1.5 % scale error injected into the gyro
    is clearly better by (J5) (every fold) and removes most of the excess cost (J6); the clean host is not."""
    s, f = host
    g0, folds0, s0 = _own(f)
    assert not clearly_better(g0, folds0), (g0, folds0)
    s2, _ = EFFECTS["gyro_scale"].inject(s, np.random.default_rng(0), strength=np.diag([1.015, 0.99, 1.01]))
    g1, folds1, s1 = _own(fit_base(s2))
    assert clearly_better(g1, folds1), (g1, folds1)
    assert s1 > 0.5, s1
