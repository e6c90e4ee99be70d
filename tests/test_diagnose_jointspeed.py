"""The joint gyro fit's faster assembly (issue 5, H7): effects/joint_normal.py's normal equations (N1) and
batched (J3) columns against independent stackings, the matrix-form re-integration against
`trajectory.reintegrate`, and the folds' reuse of the all-sample linearisation against recomputing it."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse as sp

from imugraph.diagnose.effects import joint
from imugraph.diagnose.effects.joint_normal import gyro_changes, normal_equations
from imugraph.diagnose.effects.trajectory import interval_index, reintegrate, reintegrate_matrices
from imugraph.factors.gyro import keyframe_layout
from imugraph.geometry import expmap


def _fake_fit(n=403, stride=20, seed=0):
    """A stand-in Fit with what the functions under test read: random smooth orientations, keyframes."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(np.full(n, 0.01)) + 0.003 * rng.random(n)
    kf, _ = keyframe_layout(n, stride)
    rates = 0.8 * rng.standard_normal((n, 3))
    nRb = np.empty((n, 3, 3))
    nRb[0] = expmap(rng.standard_normal(3))
    for j in range(1, n):
        nRb[j] = nRb[j - 1] @ expmap(rates[j - 1] * (t[j] - t[j - 1]))
    session = SimpleNamespace(t=t, dt=np.append(np.diff(t), np.diff(t)[-1]), gyr=rates + 0.01)
    cal = SimpleNamespace(n_mag=np.array([0.36, 0.0, 0.93]), D=np.eye(3) + 0.05 * rng.standard_normal((3, 3)))
    return SimpleNamespace(n=n, t=t, nRb=nRb, session=session, keyframe_samples=kf, calibration=cal, g=9.81,
                           info={"stride": stride}, b_gyr_bias=np.array([0.01, -0.02, 0.005]))


def _one_change(fit, d):
    """(J3) for one Δω (N, 3), written out per sample (the form before H7: einsum and np.cross)."""
    kf = np.asarray(fit.keyframe_samples, int)
    inc = np.einsum("nij,nj->ni", fit.nRb, d) * fit.session.dt[:, None]
    C = np.concatenate([np.zeros((1, 3)), np.cumsum(inc, axis=0)])
    k, s_k = interval_index(fit)
    s_next = kf[np.minimum(k + 1, len(kf) - 1)]
    has = k < len(kf) - 1
    phi = C[np.arange(fit.n)] - C[s_k]
    Phi = np.where(has[:, None], C[s_next] - C[s_k], 0.0)
    u = np.where(has, (np.arange(fit.n) - s_k) / np.maximum(s_next - s_k, 1), 0.0)
    T = np.where(has, fit.session.t[s_next] - fit.session.t[s_k], 1.0)
    bRn = np.transpose(fit.nRb, (0, 2, 1))
    dth = np.einsum("nij,nj->ni", bRn, phi - u[:, None] * Phi)
    return {"gyr": np.einsum("nij,nj->ni", bRn, Phi) / T[:, None],
            "acc": np.cross(dth, bRn @ np.array([0.0, 0.0, fit.g])),
            "mag": np.cross(dth, bRn @ fit.calibration.n_mag) @ fit.calibration.D.T}


def test_batched_gyro_changes_equal_one_change_at_a_time():
    fit = _fake_fit()
    d = np.random.default_rng(1).standard_normal((4, fit.n, 3))
    got = gyro_changes(fit, d)
    for i in range(4):
        ref = _one_change(fit, d[i])
        for c in ("gyr", "acc", "mag"):
            np.testing.assert_allclose(got[c][:, :, i], ref[c], rtol=1e-12, atol=1e-12 * np.abs(ref[c]).max())


def test_normal_equations_equal_the_stacked_sparse_and_dense_rows():
    """(N1) against Jw (sparse, six non-zeros per row on w_k, w_{k+1}) and Gd (dense, zero-padded columns)
    stacked row by row and multiplied out."""
    rng = np.random.default_rng(2)
    n, K, C = 300, 16, 7
    kf, _ = keyframe_layout(n, 20)
    K = len(kf)
    k = np.clip(np.searchsorted(kf, np.arange(n), side="right") - 1, 0, K - 1)
    J, cols, rows = {}, {}, {}
    blocks_J, blocks_G, ys, r_i, c_i = [], [], [], [], []
    row0 = 0
    for c, width in (("gyr", 4), ("acc", 4), ("mag", C)):
        idx = np.sort(rng.choice(n, 200, replace=False))
        m = len(idx)
        J[c], cols[c], y = rng.standard_normal((m, 3, 6)), rng.standard_normal((m, 3, width)), rng.standard_normal((m, 3))
        rows[c] = (idx, y)
        sel = np.concatenate([3 * k[idx][:, None] + np.arange(3), 3 * np.minimum(k[idx] + 1, K - 1)[:, None] + np.arange(3)], 1)
        r_i.append(np.repeat((row0 + np.arange(3 * m)).reshape(m, 3)[:, :, None], 6, axis=2).reshape(-1))
        c_i.append(np.repeat(sel[:, None, :], 3, axis=1).reshape(-1))
        blocks_J.append(J[c].reshape(-1))
        G = np.zeros((3 * m, C))
        G[:, :width] = cols[c].reshape(-1, width)
        blocks_G.append(G)
        ys.append(y.reshape(-1))
        row0 += 3 * m
    Jw = sp.coo_matrix((np.concatenate(blocks_J), (np.concatenate(r_i), np.concatenate(c_i))),
                       shape=(row0, 3 * K)).tocsr()
    Gd, y = np.vstack(blocks_G), np.concatenate(ys)
    Hww, Hwp, gw, GG, gp = normal_equations(J, k, cols, rows, K, C)
    np.testing.assert_allclose(Hww.toarray(), (Jw.T @ Jw).toarray(), atol=1e-10)
    np.testing.assert_allclose(Hwp, Jw.T @ Gd, atol=1e-10)
    np.testing.assert_allclose(gw, Jw.T @ y, atol=1e-10)
    np.testing.assert_allclose(GG, Gd.T @ Gd, atol=1e-10)
    np.testing.assert_allclose(gp, Gd.T @ y, atol=1e-10)


def test_matrix_reintegration_equals_reintegrate():
    from dataclasses import dataclass

    fit = _fake_fit(seed=3)
    w = 1e-2 * np.random.default_rng(4).standard_normal((len(fit.keyframe_samples), 3))
    nRk = expmap(w) @ fit.nRb[fit.keyframe_samples]
    gyr = fit.session.gyr + 1e-3

    @dataclass
    class _F:                                  # reintegrate reads these fields only
        n: int
        info: dict
        session: object
        nRb: np.ndarray
        b_gyr_bias: np.ndarray

    moved_kf = fit.nRb.copy()
    moved_kf[fit.keyframe_samples] = nRk
    ref = reintegrate(_F(fit.n, fit.info, fit.session, moved_kf, fit.b_gyr_bias), gyr)
    got = reintegrate_matrices(fit, gyr, nRk)
    np.testing.assert_allclose(got, ref, atol=1e-12)


@pytest.fixture
def small_fit():
    from imugraph.diagnose.bench import simulated_session
    from imugraph.diagnose.fit import fit_base

    return fit_base(simulated_session(11, 20.0, 100.0))


def test_fold_fit_with_the_kept_linearisation_equals_recomputing_it(small_fit, monkeypatch):
    """A fold's first Gauss–Newton step reuses the all-sample solution's linearisation: the same numbers
    as evaluating and linearising at that state again."""
    monkeypatch.setattr(joint, "ENABLED", True)
    f = small_fit
    w_rate = f.session.gyr - f.b_gyr_bias

    def exact(p):
        M = np.diag(p[:3])
        return np.linalg.solve(np.eye(3) + M, w_rate.T).T - w_rate

    train = (np.arange(f.n) // 200) % 5 != 0
    joint._START_CACHE.clear()
    joint.fit_gyro_effect(f, np.ones(f.n, bool), exact, 3, tag="t")
    kept = joint.fit_gyro_effect(f, train, exact, 3, tag="t")
    key = next(iter(joint._START_CACHE))
    fit_, start, _ = joint._START_CACHE[key]
    joint._START_CACHE[key] = (fit_, start, None)                       # recompute the first step's
    again = joint.fit_gyro_effect(f, train, exact, 3, tag="t")
    joint._START_CACHE.clear()
    np.testing.assert_allclose(kept["p"], again["p"], rtol=0, atol=1e-15)
    for c in ("gyr", "acc", "mag"):
        np.testing.assert_array_equal(kept["residuals"][c], again["residuals"][c])
