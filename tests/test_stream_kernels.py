"""The stream's per-keyframe / per-sample fast paths (imugraph.graphs.stream_kernels, StreamSmoother.push_floats)
against the general functions they replace: same noise models, same linear factors, same filtered output."""

from dataclasses import replace

import gtsam
import numpy as np
import pytest

from imugraph.graphs.cpp_velocity import split_noise
from imugraph.graphs.stream import StreamOptions, StreamSmoother
from imugraph.graphs.stream_field import field_step_factor
from imugraph.graphs.stream_interval import gauss_markov_factor
from imugraph.graphs.stream_kernels import StepBlocks, linear_step, rot_sqrt_info, split_noise_one
from imugraph.sim.scenario import distorted_session


def _spd(rng, scale=1e-6):
    A = rng.normal(size=(3, 3))
    return scale * (A @ A.T + 0.5 * np.eye(3))


def test_rot_sqrt_info_is_the_upper_cholesky_factor_of_the_information():
    """Eq. (1): U upper triangular with UᵀU = Σ⁻¹, equal to numpy's cholesky(inv(Σ))ᵀ; zero outside [:3, :3]."""
    rng = np.random.default_rng(1)
    for scale in (1e-8, 1e-5, 1.0):
        cov = _spd(rng, scale)
        out = rot_sqrt_info(cov)
        U = out[:3, :3]
        ref = np.linalg.cholesky(np.linalg.inv(cov)).T
        assert np.allclose(U, ref, rtol=1e-11, atol=0)
        assert np.allclose(U.T @ U, np.linalg.inv(cov), rtol=1e-10, atol=0)
        assert np.all(np.tril(U, -1) == 0) and np.all(out[3:] == 0) and np.all(out[:, 3:] == 0)


@pytest.mark.parametrize("huber_k", [None, 1.345])
def test_split_noise_one_whitens_as_split_noise(huber_k):
    """Both models whiten any 9-row residual as cpp_velocity.split_noise's (rotation rows: Gaussian; velocity
    rows: Huber-robust diagonal) and weight it the same."""
    rng = np.random.default_rng(2)
    cov, sig_dv = _spd(rng), 0.037
    ref = split_noise(cov[None], np.array([sig_dv]), huber_k)[0]
    got = split_noise_one(cov, sig_dv, huber_k)
    for m_ref, m_got in zip(ref, got):
        assert type(m_ref) is type(m_got)
        for _ in range(5):
            v = rng.normal(size=9) * 1e-3
            a, b = m_ref.whiten(v), m_got.whiten(v)
            assert np.allclose(a, b, rtol=1e-11, atol=1e-300)
            assert np.isclose(m_ref.loss(m_ref.squaredMahalanobisDistance(v)),
                              m_got.loss(m_got.squaredMahalanobisDistance(v)), rtol=1e-11)


def _jacobian(factor, keys):
    vals = gtsam.Values()
    for k in keys:
        vals.insert(k, np.zeros(3))
    return factor.linearize(vals).jacobian()


def test_step_blocks_equal_the_interval_factors():
    """The cached blocks give the same linear factor as gauss_markov_factor / field_step_factor, for new and
    repeated Δt_k, and the cache stays bounded."""
    sig_d = np.array([0.01, 0.02, 0.005])
    steps = StepBlocks(0.3, 0.8, sig_d, 20.0, size=4)
    for dt in (0.1, 0.1, 0.1000001, 0.25, 0.1, 0.3, 0.35, 0.4, 0.1):
        A, b = _jacobian(linear_step(7, 8, steps.velocity(dt)), (7, 8))
        A_ref, b_ref = _jacobian(gauss_markov_factor(7, 8, dt, 0.3, 0.8), (7, 8))
        assert np.array_equal(A, A_ref) and np.array_equal(b, b_ref)
        A, b = _jacobian(linear_step(3, 4, steps.field(dt)), (3, 4))
        A_ref, b_ref = _jacobian(field_step_factor(3, 4, dt, sig_d, 20.0), (3, 4))
        assert np.array_equal(A, A_ref) and np.array_equal(b, b_ref)
        assert len(steps._vel) <= 4 and len(steps._field) <= 4


def test_push_floats_is_push():
    """push_floats (the rows as ten floats, a tuple back) gives exactly push's filtered orientation, with
    missing magnetometer rows, a gyro map and θ as a state; a NaN row is counted as invalid in both."""
    session, truth = distorted_session(3, 12.0, 100.0)
    cal = truth.to_calibration()
    cal = replace(cal, gyro_map=0.01 * np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0.0]]))
    opt = StreamOptions(lag_s=1.0, fixed_lag_solver="chain", calib_states=True, disturb_detect=True)
    mag = session.mag.copy()
    mag[5::7] = np.nan
    a, b = StreamSmoother(cal, 100.0, opt), StreamSmoother(cal, 100.0, opt)
    qa, qb = [], []
    for i in range(session.n):
        qa.append(a.push(session.t[i], session.gyr[i], session.acc[i], mag[i]))
        qb.append(b.push_floats(*map(float, (session.t[i], *session.gyr[i], *session.acc[i], *mag[i]))))
        if i == 50:
            qa.append(a.push(session.t[i] + 0.001, np.array([np.nan, 0, 0]), session.acc[i]))
            qb.append(b.push_floats(float(session.t[i]) + 0.001, np.nan, 0.0, 0.0, *map(float, session.acc[i])))
            assert isinstance(qb[-1], tuple) and len(qb[-1]) == 4
    qa, qb = np.array(qa), np.array(qb)
    assert qb.shape == qa.shape and np.array_equal(qa[np.isfinite(qa)], qb[np.isfinite(qb)])
    assert np.array_equal(np.isnan(qa), np.isnan(qb)) and np.all(qa[:, 0] >= 0)
    assert a.stats.counts() == b.stats.counts() and a.stats.mag_samples < session.n
    assert a.stats.invalid == b.stats.invalid == 1
