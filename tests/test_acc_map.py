"""Tests of imugraph/calibration/acc_map.py: recovery of a known accelerometer scale/skew and offset from a simulated
multi-orientation static session, the coverage gate (one orientation; orientations about one axis), the Jacobian
against numerical derivatives, the quasi-static window selection, the invisible rotation, and map_session."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from imugraph.calibration.acc_map import (AccMapError, direction_cells, fit_acc_map, map_session, quasi_static_windows,
                                          residual_jacobian, session_acc_map)
from imugraph.io.session import Session

RATE = 100.0
G = 9.81
KA_SYM = np.array([[1.004, 0.002, -0.001], [0.002, 0.995, 0.0015], [-0.001, 0.0015, 1.003]])   # b = Ka f + ba
BA = np.array([0.05, -0.08, 0.12])                                                              # m/s²
SIGMA_ACC = 0.05                                                                                # m/s² per axis


def static_session(Ka: np.ndarray, ba: np.ndarray, rotations: Rotation, hold_s: float = 2.0, move_s: float = 1.0,
                   seed: int = 0) -> Session:
    """Holds each orientation for hold_s (f = nRbᵀ g e_z), joined by move_s of a fast turn (not quasi-static);
    b_acc = Ka f + ba + white noise SIGMA_ACC; gyro noise 0.003 rad/s."""
    rng = np.random.default_rng(seed)
    acc, gyr = [], []
    n_hold, n_move = int(hold_s * RATE), int(move_s * RATE)
    for k, r in enumerate(rotations):
        f = r.inv().apply([0.0, 0.0, G])
        acc.append(np.tile(f, (n_hold, 1)))
        gyr.append(np.zeros((n_hold, 3)))
        # between holds: a 2 rad/s spin with a shaking hand (neither window test passes)
        acc.append(f + rng.standard_normal((n_move, 3)) * 2.0)
        gyr.append(np.tile([2.0, 0.0, 0.0], (n_move, 1)))
    f_all, gyr = np.concatenate(acc), np.concatenate(gyr)
    b_acc = f_all @ Ka.T + ba + rng.standard_normal(f_all.shape) * SIGMA_ACC
    gyr = gyr + rng.standard_normal(gyr.shape) * 0.003
    n = len(b_acc)
    return Session(t=np.arange(n) / RATE, gyr=gyr, acc=b_acc, mag=np.tile([20.0, 0.0, -40.0], (n, 1)),
                   source="<sim>", name="static")


def test_recovers_known_scale_skew_and_offset():
    rots = Rotation.random(40, random_state=1)
    s = static_session(KA_SYM, BA, rots)
    m = session_acc_map(s)
    # truth, independent of the fit: f = Ka⁻¹(b − ba) ⇒ I + S = Ka⁻¹ (symmetric because Ka is)
    S_true = np.linalg.inv(KA_SYM) - np.eye(3)
    assert np.all(np.abs(m.S - S_true) < np.maximum(4 * m.std_S, 1e-4)), (m.S - S_true, m.std_S)
    assert np.all(np.abs(m.ba - BA) < np.maximum(4 * m.std_ba, 2e-3)), (m.ba - BA, m.std_ba)
    assert np.abs(m.S - S_true).max() < 5e-4 and np.abs(m.ba - BA).max() < 0.01
    assert m.n_cells >= 35 and m.rms < 0.01 < m.rms_raw
    # the corrected specific force has norm g in every held orientation (per-orientation mean: σ ≈ 0.004 m/s²)
    cells = direction_cells(quasi_static_windows(m.apply(s.acc), s.gyr, RATE))
    assert len(cells) >= 35 and np.abs(np.linalg.norm(cells, axis=1) - G).max() < 0.015


def test_rotation_of_the_axes_is_invisible():
    """Ka = Ka_sym·Q (Q: 1° about x) gives the same ellipsoid: the fit returns Ka_sym's correction, not Q's."""
    Q = Rotation.from_rotvec([np.radians(1.0), 0, 0]).as_matrix()
    rots = Rotation.random(40, random_state=2)
    m_rot = session_acc_map(static_session(KA_SYM @ Q, BA, rots, seed=5))
    # |Ka_sym Q f| = |Ka_sym f'| with f' = Q f on the same sphere: the ellipsoid is Ka_sym's
    S_true = np.linalg.inv(KA_SYM) - np.eye(3)
    assert np.abs(m_rot.S - S_true).max() < 5e-4
    assert np.abs(m_rot.ba - BA).max() < 0.01


def test_gate_fires_on_one_orientation():
    rots = Rotation.from_rotvec(np.tile([0.02, -0.01, 0.0], (30, 1)))
    s = static_session(KA_SYM, BA, rots)
    with pytest.raises(AccMapError, match=r"field 'acc': found quasi-static samples in 1 orientations"):
        session_acc_map(s)
    same, info = map_session(s)
    assert same is s and "1 orientations" in info["acc_map_gate"]


def test_gate_fires_on_orientations_about_one_axis():
    """Turned about body x only: gravity stays in the body y–z plane; the x scale/offset are not seen."""
    rots = Rotation.from_rotvec(np.c_[np.linspace(0, 2 * np.pi, 36, endpoint=False), np.zeros((36, 2))])
    s = static_session(KA_SYM, BA, rots)
    with pytest.raises(AccMapError, match="spread"):
        session_acc_map(s)


def test_jacobian_matches_numerical_derivatives():
    rng = np.random.default_rng(4)
    y = rng.standard_normal((20, 3)) * 5 + [0, 0, 5]
    p = rng.standard_normal(9) * np.r_[np.full(6, 0.01), np.full(3, 0.1)]
    r, J = residual_jacobian(p, y, G)
    Jn = np.zeros_like(J)
    h = 1e-6
    for k in range(9):
        dp = np.zeros(9); dp[k] = h
        Jn[:, k] = (residual_jacobian(p + dp, y, G)[0] - residual_jacobian(p - dp, y, G)[0]) / (2 * h)
    np.testing.assert_allclose(J, Jn, atol=1e-7, rtol=1e-6)


def test_windows_keep_holds_and_drop_motion():
    rots = Rotation.random(5, random_state=3)
    s = static_session(np.eye(3), np.zeros(3), rots)
    y = quasi_static_windows(s.acc, s.gyr, RATE, window_s=0.2)
    # 5 holds of 2 s = 10 windows of 0.2 s each; a window straddling a hold and a turn is dropped
    assert 40 <= len(y) <= 50
    assert np.abs(np.linalg.norm(y, axis=1) - G).max() < 0.1


def test_map_session_applies_the_fit():
    rots = Rotation.random(40, random_state=6)
    s = static_session(KA_SYM, BA, rots)
    out, info = map_session(s)
    assert out is not s and "acc_map" in info
    np.testing.assert_allclose(out.gyr, s.gyr)
    f_true_dir = np.linalg.solve(KA_SYM, (s.acc - BA).T).T
    assert np.abs(out.acc - f_true_dir).max() < 0.01


def test_gate_rejects_moving_windows():
    """Windows that pass the window tests but carry a 0.3 m/s² random linear acceleration: named, not returned."""
    rots = Rotation.random(40, random_state=7)
    s = static_session(np.eye(3), np.zeros(3), rots)
    rng = np.random.default_rng(8)
    y = quasi_static_windows(s.acc, s.gyr, RATE)
    y = y + rng.standard_normal(y.shape) * 0.3
    with pytest.raises(AccMapError, match="implausible|std"):
        fit_acc_map(y, source="moving")
