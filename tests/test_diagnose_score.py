"""The held-out log score (A4) of the attribution (imugraph.diagnose.score) and its use in the
significance rule (imugraph.diagnose.attribute.significant): known answers against scipy's normal density,
properness checks (a correct correction gains, a wrong one or none loses), and the case (G1) gets wrong:
removing a real high-frequency component from a residual that also carries a coloured misfit."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import norm

from imugraph.diagnose import gap as G
from imugraph.diagnose.attribute import AttributionOptions, EffectResult, significant
from imugraph.diagnose.score import GainAccumulator, channel_gain, clearly_better, log_score_sum


def _ar1(n, phi, rng):
    x = np.zeros((n, 3))
    e = rng.standard_normal((n, 3))
    for i in range(1, n):
        x[i] = phi * x[i - 1] + e[i]
    return x * np.sqrt(1 - phi ** 2)


def test_log_score_is_the_gaussian_negative_log_density():
    """Known answer: Σ −ln N(r; 0, s²) − ½ ln 2π per value, s the per-axis RMS on the training rows
    (computed here with scipy's density, independently of the module)."""
    rng = np.random.default_rng(0)
    r = rng.standard_normal((400, 3)) * [0.5, 2.0, 3.0] + [0.1, 0.0, -0.3]
    train = np.arange(400) % 3 != 0
    test = ~train
    s = np.sqrt(np.mean(r[train] ** 2, axis=0))
    expect = float(np.sum(-norm.logpdf(r[test], scale=s)) - test.sum() * 3 * 0.5 * np.log(2 * np.pi))
    assert log_score_sum(r, train, test) == pytest.approx(expect, rel=1e-12)


def test_gain_positive_for_a_real_effect_negative_for_none_or_a_wrong_one():
    """Properness on known residuals: white noise + an offset in a window. Removing the offset (fitted on
    the training rows) gains; a 'correction' that changes nothing pays its BIC cost only; one that
    removes an offset that is not there loses."""
    rng = np.random.default_rng(1)
    n = 6000
    t = np.arange(n) / 100.0
    win = (t > 20) & (t < 35)
    r0 = rng.standard_normal((n, 3))
    r0[win] += [1.5, 0.0, 0.0]
    folds = [(np.floor(t / 2.0).astype(int) % 5) == k for k in range(5)]

    def gain(correct, keep=None):
        acc = GainAccumulator()
        for f in folds:
            acc.add({"acc": r0}, {"acc": correct(~f)}, ~f, f)
        if keep is not None:
            keep.append(acc)
        return acc.result(3)

    kept = []
    real, per, n_scored = gain(lambda tr: r0 - np.where(win[:, None], r0[tr & win].mean(axis=0), 0.0), kept)
    acc_real = kept[0]
    real, per, n_scored = gain(lambda tr: r0 - np.where(win[:, None], r0[tr & win].mean(axis=0), 0.0))
    # known answer: one axis' variance 1 + 1.5² · 15/60 → 1, so ½ ln(1.5625) nats per sample
    assert real == pytest.approx(0.5 * np.log(1 + 1.5 ** 2 * 0.25), abs=0.04) and n_scored == n
    assert clearly_better(real, acc_real.fold_gains(3))
    nothing, _, _ = gain(lambda tr: r0)
    assert -1e-2 < nothing < 0.0                                     # the BIC cost 3 ln N / 2N alone
    assert not clearly_better(nothing, [nothing] * 5)
    wrong_win = (t > 40) & (t < 55)
    wrong, _, _ = gain(lambda tr: r0 - np.where(wrong_win[:, None], [1.5, 0.0, 0.0], 0.0))
    assert wrong < 0.0


def test_rows_missing_in_either_model_are_left_out():
    """NaN rows (a censored sample of the extended model) are scored for neither model."""
    rng = np.random.default_rng(2)
    r = rng.standard_normal((1000, 3))
    ext = r.copy()
    ext[::7] = np.nan
    train = np.arange(1000) % 2 == 0
    g, n = channel_gain(r, ext, train, ~train)
    ok = np.all(np.isfinite(ext), axis=1) & ~train
    assert n == ok.sum() and g == pytest.approx(0.0, abs=1e-9)


def test_log_score_sees_a_removed_component_that_the_gap_statistic_does_not():
    """The failure of (G1) measured on BROAD 01 + vibration (docs/diagnose.md §5), on known residuals:
    a coloured (AR(1)) misfit + white noise + a strong white high-frequency component. With the
    component removed and the residual rescaled to the old σ (the noise re-estimation (G1) is used
    with), (G1) against a white simulation gets WORSE (the colour of the misfit dominates); the log score,
    with each model's own σ, prefers the model without the component."""
    rng = np.random.default_rng(3)
    n, rate = 20000, 286.0
    misfit = 1.0 * _ar1(n, 0.995, rng)
    noise = 0.3 * rng.standard_normal((n, 3))
    hf = 1.2 * np.sign(np.sin(2 * np.pi * 49.6 * np.arange(n) / rate))[:, None] * rng.uniform(0.5, 1, (n, 3))
    before = misfit + noise + hf
    after = misfit + noise
    sigma = np.sqrt(np.mean(before ** 2, axis=0))
    after_rescaled = after * sigma / np.sqrt(np.mean(after ** 2, axis=0))
    sim = rng.standard_normal((n, 3)) * sigma
    mask = np.ones(n, bool)
    g_before = G.gap({"acc": before}, {"acc": sim}, {"acc": sigma}, rate, mask)["acc"]
    g_after = G.gap({"acc": after_rescaled}, {"acc": sim}, {"acc": sigma}, rate, mask)["acc"]
    assert g_after > g_before                                       # (G1) says "worse"
    train = np.arange(n) % 5 != 0
    g, _ = channel_gain(before, after, train, ~train)
    assert g > 0.2                                                  # the log score says "better"


def _res(frac, gain, penalised, folds=None):
    return EffectResult("e", "acc", 1.0, 0.5, 0.5, penalised, 4, raw_before=1.0, floor=0.1,
                        size={"value": 1.0, "threshold": 0.5}, support_fraction=frac, loglik_gain=gain,
                        loglik_folds=[gain] * 5 if folds is None else folds)


def test_significance_by_the_log_score_for_effects_scored_on_their_support():
    opt = AttributionOptions()
    assert significant(_res(0.3, 0.2, 0.0), {}, opt)               # localised, log score prefers it
    assert not significant(_res(0.3, -0.01, 0.0), {}, opt)         # localised, log score does not
    assert not significant(_res(1.0, 0.2, 0.0), {}, opt)           # global: (A2) decides
    assert not significant(_res(0.3, 0.2, 0.0, [0.5, 0.4, 0.3, 0.2, -0.01]), {}, opt)   # one fold worse
    assert significant(_res(1.0, -0.2, 0.5), {}, opt)
    low = _res(0.3, 0.2, 0.0)
    low.raw_before = 0.15                                          # raw gap below 2 × floor: never
    assert not significant(low, {}, opt)


def test_levels_are_the_held_out_scores_whose_difference_is_the_gain():
    """Known answer (scipy's density): the accumulated levels ℓ_base, ℓ_ext are the held-out negative log
    densities per sample (less ½ ln 2π per axis) with σ from the training rows; their difference is the
    per-channel gain of `result`."""
    rng = np.random.default_rng(4)
    n = 3000
    base = rng.standard_normal((n, 3)) * [2.0, 1.0, 0.5]
    ext = base * 0.5
    folds = [(np.arange(n) // 200) % 5 == k for k in range(5)]
    acc = GainAccumulator()
    expect_b = expect_e = 0.0
    for f in folds:
        acc.add({"gyr": base}, {"gyr": ext}, ~f, f)
        for r, tot in ((base, "b"), (ext, "e")):
            s = np.sqrt(np.mean(r[~f] ** 2, axis=0))
            v = float(np.sum(-norm.logpdf(r[f], scale=s)) - f.sum() * 1.5 * np.log(2 * np.pi))
            if tot == "b":
                expect_b += v
            else:
                expect_e += v
    lb, le = acc.levels()
    assert lb["gyr"] == pytest.approx(expect_b / n, rel=1e-10)
    assert le["gyr"] == pytest.approx(expect_e / n, rel=1e-10)
    assert lb["gyr"] - le["gyr"] == pytest.approx(3 * np.log(2.0), rel=1e-10)       # every σ halved
    assert lb["gyr"] - le["gyr"] == pytest.approx(acc.result(0)[1]["gyr"], rel=1e-12)
    assert np.isnan(lb["acc"])                                                       # channel not given


def test_injected_part_logscore_shrink_known_answers():
    """Known answers: the injection added 0.8 nats per sample over the clean host (acc 0.7, mag 0.1), the
    correction leaves 0.2 → 0.75; below the host → 1; localised, wrong, or hostless → None."""
    from imugraph.diagnose.harness import _host_loglik, injected_part_logscore_shrink

    host_diag = {"effects": [{"name": "x", "support_fraction": 1.0,
                              "loglik_base_per_channel": {"gyr": 1.0, "acc": 2.0, "mag": 3.0}},
                             {"name": "w", "support_fraction": 0.2,
                              "loglik_base_per_channel": {"gyr": 9.0, "acc": 9.0, "mag": 9.0}}]}
    hosts = {"h": _host_loglik(host_diag)}
    assert set(hosts["h"]) == {"x"}
    case = {"correct": True, "host": "h", "verdict": "x", "won": {"support_fraction": 1.0},
            "loglik": {"loglik_base_per_channel": {"gyr": 1.0, "acc": 2.7, "mag": 3.1},
                       "loglik_ext_per_channel": {"gyr": 1.0, "acc": 2.1, "mag": 3.1}}}
    assert injected_part_logscore_shrink(case, hosts) == pytest.approx(0.75)
    better = dict(case, loglik={**case["loglik"], "loglik_ext_per_channel": {"gyr": 0.9, "acc": 1.9, "mag": 3.0}})
    assert injected_part_logscore_shrink(better, hosts) == pytest.approx(1.0)
    assert injected_part_logscore_shrink(dict(case, won={"support_fraction": 0.3}), hosts) is None
    assert injected_part_logscore_shrink(dict(case, correct=False), hosts) is None
    assert injected_part_logscore_shrink(dict(case, host="other"), hosts) is None
