"""Second stage of the attribution (imugraph.diagnose.refit) and the verdict rule: full refit of an
effect that bent the base fit, the effects' data-level corrections, their physical sizes (relevance) and
the verdict = significant AND relevant."""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.diagnose.attribute import AttributionOptions, EffectResult, NONE, significant, verdict
from imugraph.diagnose.bench import simulated_session
from imugraph.diagnose.effects import EFFECTS
from imugraph.diagnose.fit import fit_base
from imugraph.diagnose.refit import on_session, refit_effect, rescale


@pytest.fixture(scope="module")
def clean():
    s = simulated_session(4, 30.0, 100.0)
    return s, fit_base(s)


def test_on_session_of_its_own_session_is_the_fit(clean):
    _, f = clean
    g = on_session(f, f.session)
    for c in ("gyr", "acc", "mag"):
        np.testing.assert_array_equal(g.residuals[c], f.residuals[c])


@pytest.mark.parametrize("name", ["accelerometer_bias", "time_offset", "gyro_scale", "magnetic_disturbance"])
def test_corrected_measurements_give_the_corrected_residuals(clean, name):
    """y' from Correction.corrected, evaluated against the same fit, equals the correction's raw residuals
    (acc, mag: (R2)–(R3) directly; the gyro through Δω)."""
    s, _ = clean
    s2, _ = EFFECTS[name].inject(s, np.random.default_rng(2))
    f = fit_base(s2)
    corr = EFFECTS[name].fit(f, np.ones(f.n, bool))
    new = corr.corrected(f)
    raw = corr.raw_residuals(f)
    pred = f.predicted()
    for c in ("acc",) if name == "accelerometer_bias" else ():
        np.testing.assert_allclose(new[c] - pred[c], raw[c], atol=1e-9)
    if name == "magnetic_disturbance":          # the refit leaves the windows' field samples out
        assert np.isnan(new["mag"]).sum() > np.isnan(s2.mag).sum()
        m = np.isfinite(new["mag"]).all(axis=1)
        np.testing.assert_array_equal(new["mag"][m], f.session.mag[m])     # the field on the gyro's time base (B3')
    if "d_omega" in corr.deltas:      # a jointly fitted gyro effect hands on its own Δω (the bias is the refit's)
        np.testing.assert_allclose(new["gyr"], s2.gyr + corr.deltas.get("d_effect", corr.deltas["d_omega"]))


def test_refit_recovers_an_accelerometer_bias_the_base_fit_absorbed(clean):
    """Known answer: the injected δ_a. The first-order fit on the base fit sees only the part the tilted
    base fit left in the residuals; the refit (trajectory refitted on the corrected data) recovers it."""
    s, _ = clean
    bias = np.array([0.25, -0.2, 0.1])
    s2, _ = EFFECTS["accelerometer_bias"].inject(s, np.random.default_rng(0), strength=np.linalg.norm(bias))
    true = np.asarray(s2.acc - s.acc)[0]
    f = fit_base(s2)
    first = np.asarray(EFFECTS["accelerometer_bias"].fit(f, np.ones(f.n, bool)).params["bias_ms2"])
    ext, info = refit_effect(EFFECTS["accelerometer_bias"], f, rounds=2)
    assert info["changed"]
    corr = EFFECTS["accelerometer_bias"].fit(ext, np.ones(f.n, bool))
    est = np.asarray(corr.params["bias_ms2"])
    assert np.linalg.norm(est - true) < 0.3 * np.linalg.norm(true)
    assert np.linalg.norm(est - true) < np.linalg.norm(first - true)
    size = EFFECTS["accelerometer_bias"].size(corr, ext)
    assert size["value"] == pytest.approx(np.linalg.norm(est)) and size["value"] >= size["threshold"]


def test_rescale_leaves_the_gyro_and_restores_the_base_level(clean):
    _, f = clean
    after = {c: 0.5 * f.residuals[c] for c in ("gyr", "acc", "mag")}
    out = rescale(after, f, np.ones(f.n, bool))
    np.testing.assert_array_equal(out["gyr"], after["gyr"])
    for c in ("acc", "mag"):
        np.testing.assert_allclose(np.nanstd(out[c], axis=0), np.nanstd(f.residuals[c], axis=0), rtol=1e-6)


@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_clean_session_effects_are_below_relevance(clean, name):
    """Data from the model: every fitted effect's physical size stays below its threshold."""
    _, f = clean
    corr = EFFECTS[name].fit(f, np.ones(f.n, bool))
    size = EFFECTS[name].size(corr, f)
    assert set(size) >= {"value", "threshold", "unit"}
    assert size["value"] < size["threshold"], size


@pytest.mark.parametrize("name,strength,seed", [("time_offset", 0.03, 2),     # seed 2: an accelerometer delay
                                                ("gyro_scale", np.eye(3) * 1.02, 5), ("vibration", 1.5, 5)])
def test_injected_effects_reach_relevance(clean, name, strength, seed):
    s, _ = clean
    s2, _ = EFFECTS[name].inject(s, np.random.default_rng(seed), strength=strength)
    f = fit_base(s2)
    corr = EFFECTS[name].fit(f, np.ones(f.n, bool))
    size = EFFECTS[name].size(corr, f)
    assert size["value"] >= size["threshold"], size


def _result(name, penalised, value, threshold, raw_before=1.0, channel="acc"):
    return EffectResult(name, channel, 0.9, 0.1, 0.9, penalised, 3, raw_before=raw_before,
                        size={"value": value, "threshold": threshold, "unit": ""})


def test_verdict_needs_significance_and_relevance():
    opt = AttributionOptions()
    floor = {"gyr": 0.1, "acc": 0.1, "mag": 0.1}
    big_small = _result("a", 0.9, 0.5, 1.0)                 # significant, below relevance
    ok = _result("b", 0.6, 2.0, 1.0)                        # significant and relevant
    weak = _result("c", 0.1, 5.0, 1.0)                      # relevant, not significant
    near_floor = _result("d", 0.9, 5.0, 1.0, raw_before=0.15)   # raw gap near the noise floor
    assert significant(big_small, floor, opt) and not significant(weak, floor, opt)
    assert not significant(near_floor, floor, opt)
    assert verdict([big_small, ok, weak], floor, opt) == "b"
    assert verdict([big_small, weak, near_floor], floor, opt) == NONE
    assert big_small.as_dict()["relevant"] is False and ok.as_dict()["relevant"] is True


def test_joint_refit_of_a_magnet_recovers_offset_and_window(clean):
    """magnetic_disturbance is refitted jointly (calibration with windowed hard-iron offsets): the
    effect fitted against that θ* recovers the injected body-frame field and its window."""
    from imugraph.diagnose.harness import interval_iou

    s, _ = clean
    E = EFFECTS["magnetic_disturbance"]
    s2, truth = E.inject(s, np.random.default_rng(3), window=(12.0, 22.0), strength=40.0)
    f = fit_base(s2)
    ext, info = refit_effect(E, f)
    assert info.get("joint") == {"disturbance_windows": True}
    corr = E.fit(ext, np.ones(f.n, bool))
    est = np.asarray(corr.params["windows"][0]["body_offset"])
    true = np.asarray(truth["params"]["vector"])
    assert np.linalg.norm(est - true) < 0.15 * np.linalg.norm(true)
    assert interval_iou((truth["t_start"], truth["t_end"]), (corr.t_start, corr.t_end)) > 0.7
    assert E.size(corr, ext)["value"] >= E.size(corr, ext)["threshold"]


def test_gyro_exact_is_the_first_order_refit_where_the_body_turns_little(clean):
    """gyro_exact (samples re-integrated between fixed keyframes) against gyro_refit (E1)–(E3), which sums
    the body-frame changes Δω_i Δt_i without carrying them through the rotation inside the interval: the
    two agree where the body turns little within the keyframe interval (< 0.05 rad), and differ (the linear
    form's error, linear in Δω) where it turns fast; zero change gives the fit's own residuals."""
    from imugraph.diagnose.effects.base import gyro_exact, gyro_refit, interval_index

    _, f = clean
    z = gyro_exact(f, np.zeros((f.n, 3)))
    for c in ("gyr", "acc", "mag"):
        np.testing.assert_array_equal(z[c], f.residuals[c])
    w = f.session.gyr - f.b_gyr_bias
    d = 0.01 * w[:, [1, 2, 0]]
    ex, lin = gyro_exact(f, d), gyro_refit(f, d)[0]
    k, _ = interval_index(f)
    turn = np.bincount(k, np.linalg.norm(w, axis=1) * f.session.dt)[k]           # rotation in the interval
    for sel, bound in ((turn < 0.05, 0.1), (turn > 0.3, None)):
        change = np.abs(ex["acc"][sel] - f.residuals["acc"][sel])
        diff = np.abs(ex["acc"][sel] - lin["acc"][sel])
        ratio = np.nansum(diff) / np.nansum(change)
        if bound is not None:
            assert ratio < bound, ratio
        else:
            assert ratio > 0.1, ratio


def test_on_session_reintegrates_the_original_gyro(clean):
    """θ* fitted on corrected gyro data, seen on the original data: the samples between keyframes follow the
    original gyro, so removing the correction exactly (gyro_exact with Δω = y' − y) gives back the residuals
    of θ* on the corrected data (to the bias-linearisation point of the fit's own integration)."""
    from imugraph.diagnose.effects.base import gyro_exact, replace_session

    s, f = clean
    S = np.eye(3) + np.diag([0.02, -0.015, 0.01])
    orig = replace_session(s, gyr=s.gyr @ S.T)
    view = on_session(f, orig)
    assert not np.allclose(view.nRb, f.nRb)
    np.testing.assert_allclose(view.nRb[f.keyframe_samples], f.nRb[f.keyframe_samples], atol=1e-12)
    back = gyro_exact(view, s.gyr - orig.gyr)
    ok = np.isfinite(f.residuals["gyr"]).all(axis=1)
    err = np.abs(back["gyr"][ok] - f.residuals["gyr"][ok]) / f.sigma["gyr"]
    assert np.max(err) < 0.5 and np.mean(err) < 0.05, (np.max(err), np.mean(err))
