"""Gyro effects estimated jointly with the trajectory (imugraph.diagnose.effects.joint, issue 5 G6) and the
magnetometer's sub-sample lag in the base model's prediction (imugraph.diagnose.fit (B3'))."""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.diagnose.bench import simulated_session
from imugraph.diagnose.effects import EFFECTS
from imugraph.diagnose.effects.base import replace_session
from imugraph.diagnose.effects.gyro_bias_drift import legendre_basis
from imugraph.diagnose.effects.joint import _keyframe_jacobian, evaluate, moved
from imugraph.diagnose.effects.joint_normal import gyro_changes
from imugraph.diagnose.fit import fit_base, subsample_lag_offset
from imugraph.diagnose.refit import refit_effect
from imugraph.geometry import expmap


@pytest.fixture(autouse=True)
def joint_on(monkeypatch):
    """The joint estimator is opt-in (effects/joint.ENABLED): these tests are about it."""
    import imugraph.diagnose.effects.joint as joint

    monkeypatch.setattr(joint, "ENABLED", True)


@pytest.fixture(scope="module")
def clean():
    s = simulated_session(7, 30.0, 100.0)
    return s, fit_base(s)


def _state(f, w=None):
    K = len(f.keyframe_samples)
    return {"p": np.zeros(0), "bias": np.zeros(3), "w": np.zeros((K, 3)) if w is None else w, "q": np.zeros(13)}


def test_keyframe_jacobian_matches_numerical_derivative(clean):
    """(J2): the residual change of a small keyframe rotation vs the exact re-evaluation."""
    _, f = clean
    K = len(f.keyframe_samples)
    w = 1e-5 * np.random.default_rng(0).standard_normal((K, 3))
    zero = lambda p: np.zeros((f.n, 3))          # noqa: E731
    r0 = evaluate(f, _state(f), zero).residuals
    r1 = evaluate(f, _state(f, w), zero).residuals
    cur = evaluate(f, _state(f), zero)
    m = cur.info["mag_calibration"]
    J, k, k1 = _keyframe_jacobian(cur, m["D"], m["n_nav"])
    x = np.concatenate([w[k], w[k1]], axis=1)
    for c in ("gyr", "acc", "mag"):
        lin = np.einsum("nij,nj->ni", J[c], x)
        num = r1[c] - r0[c]
        ok = np.all(np.isfinite(num), axis=1) & (np.arange(f.n) < f.keyframe_samples[-1])
        err = np.linalg.norm(lin[ok] - num[ok]) / np.linalg.norm(num[ok])
        assert err < 0.02, (c, err)


def test_gyro_change_matches_exact_reintegration(clean):
    """(J3): the first-order residual change of a small gyro change (rotation inside the intervals
    carried in the nav frame) vs `moved` (exact re-integration, keyframes fixed)."""
    _, f = clean
    d = 2e-5 * np.random.default_rng(1).standard_normal((f.n, 3)) + 3e-5
    w0 = np.zeros((len(f.keyframe_samples), 3))
    base = moved(f, w0, np.zeros((f.n, 3)))    # the samples re-integrated at the fit's bias: the linearisation point
    lin = {c: v[:, :, 0] for c, v in gyro_changes(base, d[None]).items()}   # one change
    ex = moved(f, w0, d).residuals
    for c in ("gyr", "acc", "mag"):
        num = ex[c] - base.residuals[c]
        ok = np.all(np.isfinite(num), axis=1) & (np.arange(f.n) < f.keyframe_samples[-1])
        err = np.linalg.norm(lin[c][ok] - num[ok]) / np.linalg.norm(num[ok])
        assert err < 0.05, (c, err)


def test_joint_gyro_scale_recovers_the_injected_symmetric_part(clean):
    """Known answer: a symmetric scale/non-orthogonality M injected into a simulation is recovered
    (the alternation of the keyframes-fixed fit recovered a fraction of it); the clean host gives ≈ 0."""
    s, f = clean
    M = np.array([[0.02, 0.006, -0.004], [0.006, -0.015, 0.003], [-0.004, 0.003, 0.01]])
    s2, _ = EFFECTS["gyro_scale"].inject(s, np.random.default_rng(0), strength=np.eye(3) + M)
    f2 = fit_base(s2)
    est = np.asarray(EFFECTS["gyro_scale"].fit(f2, np.ones(f2.n, bool)).params["M"])
    np.testing.assert_allclose(est, M, atol=1e-3)
    est0 = np.asarray(EFFECTS["gyro_scale"].fit(f, np.ones(f.n, bool)).params["M"])
    assert np.linalg.norm(est0, 2) < 1e-3


def test_joint_refit_converges(clean):
    """The refit's rounds reach a fixed point: 1 and 3 rounds give the same M (the alternation with the
    keyframes fixed grew round after round, docs/diagnose.md §4 G2)."""
    s, _ = clean
    M = np.diag([0.015, -0.01, 0.02])
    s2, _ = EFFECTS["gyro_scale"].inject(s, np.random.default_rng(0), strength=np.eye(3) + M)
    f2 = fit_base(s2)
    sizes = []
    for rounds in (1, 3):
        th, _ = refit_effect(EFFECTS["gyro_scale"], f2, rounds=rounds)
        sizes.append(np.asarray(EFFECTS["gyro_scale"].fit(th, np.ones(th.n, bool)).params["M"]))
    np.testing.assert_allclose(sizes[0], sizes[1], atol=2e-4)
    np.testing.assert_allclose(sizes[1], M, atol=1e-3)


def test_joint_drift_recovers_an_injected_ramp(clean):
    """Known answer: a linear bias ramp of 0.5 °/s (in the Legendre span) on one axis."""
    s, f = clean
    t = s.t
    ramp = np.deg2rad(0.5) * (t - t[0]) / (t[-1] - t[0])
    s2 = replace_session(s, gyr=s.gyr + np.outer(ramp, [0.0, 1.0, 0.0]))
    f2 = fit_base(s2)
    B = legendre_basis(t, t[0], t[-1])

    def beta(fit):
        corr = EFFECTS["gyro_bias_drift"].fit(fit, np.ones(fit.n, bool))
        return B @ np.asarray(corr.params["legendre_coefficients_rad_s"])

    # the estimator is linear in the data: the injected fit minus the host's own (estimation noise of the
    # simulated host: 0.04–0.17 °/s p-p on 30 s at 100 Hz) is the ramp (its mean goes to the constant bias)
    diff = np.rad2deg(beta(f2) - beta(f))
    want = np.rad2deg(np.outer(ramp - ramp.mean(), [0.0, 1.0, 0.0]))
    np.testing.assert_allclose(diff - diff.mean(axis=0), want, atol=0.03)


def test_subsample_lag_offset_known_answer(clean):
    """(B3'): the field predicted at R(t − τ) = R Exp(−τω), by a constant turn about z, independently:
    body at angle θ sees bRn n; τ earlier it was at θ − τω."""
    _, f = clean
    from dataclasses import replace

    th = np.linspace(0, 2.0, f.n)
    rate = np.array([0.0, 0.0, 3.0])
    nRb = expmap(np.outer(th, [0, 0, 1.0]))
    g = replace(f, nRb=nRb, b_omega=np.tile(rate, (f.n, 1)))
    tau = 0.004
    got = subsample_lag_offset(g, tau)
    D, n = np.asarray(f.calibration.D), f.calibration.n_mag
    earlier = expmap(np.outer(th - tau * 3.0, [0, 0, 1.0]))
    want = (np.transpose(earlier, (0, 2, 1)) @ n) @ D.T - (np.transpose(nRb, (0, 2, 1)) @ n) @ D.T
    np.testing.assert_allclose(got, want, atol=1e-12)
