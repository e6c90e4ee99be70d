"""The stream's speed-written arithmetic (issue 3, real-time margin) against the general functions it replaces:
written out for one keyframe interval, the same math to rounding (known answers computed by other code)."""

import numpy as np
import pytest

from imugraph.calibration.acc_timing import turn_back
from imugraph.factors.field import field_steps
from imugraph.factors.velocity import gauss_markov
from imugraph.geometry import expmap, quat_normalize, quat_to_rotmat
from imugraph.graphs.stream_calib import OnlineMagCalibration
from imugraph.graphs.stream_field import field_key, field_step_factor
from imugraph.graphs.stream_interval import chain, gauss_markov_factor, q2R, qstep, turn_back_rows
from imugraph.sim.scenario import distorted_session
from imugraph.graphs.stream_run import bootstrap_calibration
from imugraph import keys

import gtsam


def test_turn_back_rows_is_turn_back():
    """Rodrigues on the vector (eq. 5) = the (n, 3, 3) expmap of acc_timing.turn_back, incl. zero and tiny turns."""
    rng = np.random.default_rng(3)
    a, w, dt = rng.normal(size=(40, 3)) * 9.0, rng.normal(size=(40, 3)) * 3.0, rng.uniform(0.002, 0.02, 40)
    w[5] = 0.0
    w[6] = 1e-7
    for frac in (0.0, 0.3, 0.97):
        assert np.allclose(turn_back_rows(a, w, dt, frac), turn_back(a, w, dt, frac), rtol=0, atol=1e-12)
    assert turn_back_rows(a[:0], w[:0], dt[:0], 0.5).shape == (0, 3)


def test_q2R_is_quat_to_rotmat():
    q = quat_normalize(np.random.default_rng(4).normal(size=(64, 4)))
    assert np.allclose(q2R(q), quat_to_rotmat(q), rtol=0, atol=1e-14)
    assert np.allclose(q2R(np.array([[1.0, 0, 0, 0]]))[0], np.eye(3), atol=0)


def test_chain_is_qstep_and_expmap():
    """The written-out chain equals repeated qstep (bit for bit) and the product of expmaps (rotation matrices)."""
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(0.003, 0.004, 31))
    w, b = rng.normal(size=(30, 3)), rng.normal(size=3) * 0.01
    w[3] = b                                                   # zero turn: the series branch
    q, ref = chain(t, w, b), [(1.0, 0.0, 0.0, 0.0)]
    for j in range(30):
        ref.append(qstep(ref[-1], *(w[j] - b), t[j + 1] - t[j]))
    assert np.array_equal(q, np.array(ref))
    R = np.eye(3)
    for j in range(30):
        R = R @ expmap((w[j] - b) * (t[j + 1] - t[j]))
    assert np.allclose(q2R(q[-1:])[0], R, atol=1e-12)


@pytest.mark.parametrize("dt", [0.1, 0.0345, 5.0])
def test_scalar_coefficients_are_the_array_ones(dt):
    """gauss_markov_factor / field_step_factor use scalar φ, σ_w: the same whitened residual as the array functions."""
    rng = np.random.default_rng(6)
    v0, v1 = rng.normal(size=3), rng.normal(size=3)
    values = gtsam.Values()
    values.insert(keys.vel(0), v0)
    values.insert(keys.vel(1), v1)
    phi, sig = gauss_markov(np.array([dt]), 0.5, 2.0)
    r = (v1 - phi[0] * v0) / sig[0]
    assert np.isclose(gauss_markov_factor(keys.vel(0), keys.vel(1), dt, 0.5, 2.0).error(values), 0.5 * r @ r, rtol=1e-13)
    values = gtsam.Values()
    values.insert(field_key(0), v0)
    values.insert(field_key(1), v1)
    sig_d = (1.0, 2.0, 0.5)
    phi, sig_w = field_steps(np.array([dt]), sig_d, 30.0)
    r = (v1 - phi[0] * v0) / sig_w[0]
    assert np.isclose(field_step_factor(field_key(0), field_key(1), dt, sig_d, 30.0).error(values), 0.5 * r @ r, rtol=1e-13)


def test_calib_add_sums_are_direct_sums():
    """OnlineMagCalibration.add: S = Σ ξ ξᵀ over the kept rows, ξ = (u, w, 1, y) (NaN rows and gated rows out),
    and forget scales it; computed directly here."""
    session, _ = distorted_session(5, 20.0, 100.0)
    cal, _ = bootstrap_calibration(session, 15.0)
    oc = OnlineMagCalibration(cal)
    rng = np.random.default_rng(7)
    R = expmap(rng.normal(size=(25, 3)))
    c = cal
    u, w = R[:, 0, :], -R[:, 2, :]
    y = (np.cos(c.dip_rad) * u + np.sin(c.dip_rad) * w) @ c.D.T + c.o + rng.normal(size=(25, 3)) * 0.01 * oc.scale
    y[3] = np.nan
    y[7] += 10 * oc.scale                                     # gated
    assert oc.add(y, R) == 23 and oc.rejected == 1
    keep = np.ones(25, bool)
    keep[[3, 7]] = False
    xi = np.hstack([u[keep], w[keep], np.ones((23, 1)), y[keep]])
    assert np.allclose(oc.S, xi.T @ xi, rtol=1e-13, atol=0)
    oc.forget(0.5)
    assert np.allclose(oc.S, 0.5 * xi.T @ xi, rtol=1e-13, atol=0)
    assert oc.add(np.full((4, 3), np.nan), R[:4]) == 0
