"""The stream's nav-field perturbation (imugraph.graphs.stream_field): the CustomFactor's error and Jacobians
against numerical derivatives, the Gauss–Markov step against its closed form, and a stream with it."""

import gtsam
import numpy as np
import pytest

from imugraph.calibration.result import n_mag_from_dip
from imugraph.graphs.cpp_velocity import pose_key
from imugraph.graphs.stream import StreamOptions, StreamSmoother
from imugraph.graphs.stream_field import field_key, field_mag_factor, field_start_prior, field_step_factor

UNIT3 = gtsam.noiseModel.Unit.Create(3)


def _values(R, p, d):
    v = gtsam.Values()
    v.insert(pose_key(0), gtsam.Pose3(gtsam.Rot3(R), p))
    v.insert(field_key(0), np.asarray(d, float))
    return v


def test_field_factor_error_known_answer():
    """R = identity, d = 0: e = n − m̄; a 90° turn about z maps the nav x axis to body −y (Rᵀ e_x)."""
    n, m = n_mag_from_dip(np.deg2rad(60.0)), np.array([0.1, 0.2, -0.3])
    f = field_mag_factor(pose_key(0), field_key(0), m, n, UNIT3)
    assert np.allclose(f.unwhitenedError(_values(np.eye(3), np.zeros(3), np.zeros(3))), n - m, atol=1e-14)
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])          # body x → nav y
    d = np.array([0.01, -0.02, 0.03])
    f0 = field_mag_factor(pose_key(0), field_key(0), np.zeros(3), np.array([1.0, 0.0, 0.0]), UNIT3)
    e = f0.unwhitenedError(_values(Rz, np.zeros(3), d))
    assert np.allclose(e, [0.0 + d[1], -1.0 - d[0], d[2]], atol=1e-14)          # Rzᵀ(e_x + d)


def test_field_factor_jacobians_numerical():
    rng = np.random.default_rng(3)
    n, m = n_mag_from_dip(np.deg2rad(67.0)), rng.normal(size=3)
    R = gtsam.Rot3.Expmap(rng.normal(size=3)).matrix()
    x = _values(R, rng.normal(size=3), 0.02 * rng.normal(size=3))
    f = field_mag_factor(pose_key(0), field_key(0), m, n, UNIT3)
    lin = f.linearize(x)
    A = lin.jacobian()[0]                   # [pose (6) | d (3)], whitened = raw with a unit model
    e0 = f.unwhitenedError(x)
    h, num = 1e-6, np.zeros((3, 9))
    for i in range(9):
        delta = gtsam.VectorValues()
        step = np.zeros(9)
        step[i] = h
        delta.insert(pose_key(0), step[:6])
        delta.insert(field_key(0), step[6:])
        num[:, i] = (f.unwhitenedError(x.retract(delta)) - e0) / h
    order = [lin.keys().index(pose_key(0)), lin.keys().index(field_key(0))]
    A_sorted = np.hstack([A[:, :6], A[:, 6:]]) if order == [0, 1] else np.hstack([A[:, 3:], A[:, :3]])
    assert np.allclose(A_sorted, num, atol=1e-5)
    assert np.allclose(num[:, 3:6], 0.0, atol=1e-8)          # the position does not enter


def test_gauss_markov_step_closed_form():
    """(d1 − φ d0)/σ_w per axis, φ = exp(−Δt/τ), σ_w = σ_d √(1 − φ²): the factor's error is ½ Σ of its square."""
    sig, dt, tau = np.array([0.015, 0.003, 0.015]), 0.1, 1.0
    d0, d1 = np.array([0.01, -0.002, 0.004]), np.array([0.012, 0.001, -0.003])
    v = gtsam.Values()
    v.insert(field_key(0), d0)
    v.insert(field_key(1), d1)
    phi = np.exp(-dt / tau)
    r = (d1 - phi * d0) / (sig * np.sqrt(1 - phi**2))
    assert np.isclose(field_step_factor(field_key(0), field_key(1), dt, sig, tau).error(v), 0.5 * r @ r, rtol=1e-10)
    assert np.isclose(field_start_prior(field_key(0), sig).error(v), 0.5 * np.sum((d0 / sig) ** 2), rtol=1e-10)


@pytest.fixture(scope="module")
def case():
    from imugraph.sim.scenario import distorted_session

    session, truth = distorted_session(3, 20.0, 100.0)
    return session, truth.to_calibration()


@pytest.mark.parametrize("lag", [None, 2.0])
def test_stream_with_field_matches_truth(case, lag):
    """A homogeneous simulated field: the perturbation stays within its prior (|d| ≲ 3 σ_d) and the smoothed
    orientation is as accurate as without it (the estimated d does not pull the orientation)."""
    from imugraph.evaluate import orientation_error
    from imugraph.graphs.stream_run import stream_session

    session, cal = case
    errs = {}
    for name, sig in (("field", (0.015, 0.003, 0.015)), ("none", None)):
        r = stream_session(session, cal, StreamOptions(lag_s=lag, online_calibration=False, field_sigma=sig))
        assert r.counts["failed_updates"] == 0
        errs[name] = orientation_error(r.smoothed, session.quat, None, 100.0).rms_deg
    assert errs["field"] < errs["none"] + 0.1 and errs["field"] < 1.0
    sm = StreamSmoother(cal, 100.0, StreamOptions(lag_s=lag, online_calibration=False), g0=9.81)
    for i in range(session.n):
        sm.push(session.t[i], session.gyr[i], session.acc[i], session.mag[i])
    assert np.all(np.abs(sm._d) < 3 * np.array([0.015, 0.003, 0.015]))
