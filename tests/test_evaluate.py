"""Tests of imugraph.evaluate: heading offset and time shift removed, tilt kept, NaN and mask handling.

Trajectories are built with scipy's Rotation (independent of the code under test) from an analytic
rotation-vector path, so the shifted estimate is exact at fractional sample times.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from imugraph.errors import ImugraphError
from imugraph.evaluate import (OrientationScore, field_norm_error, heading_error, inclination_error,
                               orientation_error, shift_quat)

RATE = 100.0
N = 6000


def _rotvec_path(t: np.ndarray) -> np.ndarray:
    """A smooth 3-D motion: (N, 3) rotation vectors with rates up to ≈ 1.5 rad/s."""
    return np.stack([0.8 * np.sin(0.7 * t), 0.6 * np.cos(0.5 * t + 1.0), 1.5 * np.sin(0.3 * t + 2.0)], axis=1)


def _wxyz(rot: Rotation) -> np.ndarray:
    q = rot.as_quat()  # scipy: x, y, z, w
    return np.concatenate([q[:, 3:], q[:, :3]], axis=1)


def _reference() -> np.ndarray:
    return _wxyz(Rotation.from_rotvec(_rotvec_path(np.arange(N) / RATE)))


def _estimate(heading_deg: float = 0.0, lag_samples: float = 0.0, tilt_deg: float = 0.0) -> np.ndarray:
    """nRb_est(k) = Rz(−ψ) · Rx(tilt) · nRb_ref(t_k − lag), so nRb_ref ≈ Rz(ψ) nRb_est when tilt = 0."""
    t = (np.arange(N) - lag_samples) / RATE
    left = Rotation.from_euler("z", -heading_deg, degrees=True)
    left = left * Rotation.from_euler("x", tilt_deg, degrees=True)
    return _wxyz(left * Rotation.from_rotvec(_rotvec_path(t)))


def test_heading_offset_and_shift_are_removed():
    score = orientation_error(_estimate(30.0, 1.25), _reference(), None, RATE)
    assert isinstance(score, OrientationScore)
    assert score.rms_deg < 0.05
    assert score.heading_offset_deg == pytest.approx(30.0, abs=0.01)
    assert score.shift_samples == pytest.approx(1.25)
    assert score.shift_s == pytest.approx(1.25 / RATE)
    assert score.n == N - 2 * 4  # ceil(3) + 1 samples dropped at each end


def test_negative_shift_and_heading_sign():
    score = orientation_error(_estimate(-100.0, -2.0), _reference(), None, RATE)
    assert score.rms_deg < 0.05
    assert score.heading_offset_deg == pytest.approx(-100.0, abs=0.01)
    assert score.shift_samples == pytest.approx(-2.0)


def test_without_heading_removal_the_offset_counts():
    score = orientation_error(_estimate(30.0, 0.0), _reference(), None, RATE, heading=False)
    assert score.rms_deg == pytest.approx(30.0, abs=0.01)
    assert score.heading_offset_deg == 0.0


def test_constant_tilt_is_not_removed():
    ref = _reference()
    est = _estimate(30.0, 1.25, tilt_deg=2.0)
    score = orientation_error(est, ref, None, RATE)
    assert score.rms_deg == pytest.approx(2.0, abs=0.05)
    assert score.max_deg == pytest.approx(2.0, abs=0.1)
    incl = inclination_error(est, ref, None, RATE)
    assert incl.rms_deg == pytest.approx(2.0, abs=0.05)
    assert heading_error(est, ref, None, RATE).rms_deg < 0.1


def test_heading_drift_shows_in_heading_not_inclination():
    ref = _reference()
    drift = np.linspace(-5.0, 5.0, N)  # degrees, zero mean: the constant offset cannot remove it
    rot_drift = Rotation.from_euler("z", drift[:, None], degrees=True)
    est = _wxyz(rot_drift * Rotation.from_rotvec(_rotvec_path(np.arange(N) / RATE)))
    rms_expected = np.sqrt(np.mean(drift[1:-1] ** 2))  # no shift search: a shift would absorb some drift
    assert heading_error(est, ref, None, RATE, max_shift=0).rms_deg == pytest.approx(rms_expected, rel=1e-3)
    assert inclination_error(est, ref, None, RATE, max_shift=0).rms_deg < 1e-6
    assert heading_error(est, ref, None, RATE).rms_deg <= rms_expected + 1e-9


def test_nan_reference_rows_are_ignored():
    ref = _reference()
    est = _estimate(30.0, 1.25)
    ref[1000:2000] = np.nan
    est[1010:1990] = np.array([0.0, 1.0, 0.0, 0.0])  # wrong where only NaN truth exists
    score = orientation_error(est, ref, None, RATE)
    assert score.rms_deg < 0.05
    assert score.n == N - 8 - 1000


def test_mask_is_respected():
    ref = _reference()
    est = _estimate(0.0, 0.0)
    mask = np.zeros(N, bool)
    mask[2000:4000] = True
    est[:1900] = _estimate(0.0, 0.0, tilt_deg=20.0)[:1900]  # large error outside the mask only
    score = orientation_error(est, ref, mask, RATE)
    assert score.rms_deg < 0.05
    assert score.n == 2000
    full = orientation_error(est, ref, None, RATE)
    assert full.rms_deg > 5.0


def test_nan_estimate_rows_are_skipped_with_their_neighbours():
    est = _estimate(0.0, 0.0)
    est[3000] = np.nan
    score = orientation_error(est, _reference(), None, RATE)
    assert np.isfinite(score.rms_deg) and score.rms_deg < 0.05
    assert score.n == N - 8 - 9  # the bad row and every row within ±4 samples of it


def test_shift_quat_halfway_is_half_the_rotation():
    quat = _wxyz(Rotation.from_euler("z", [[0.0], [10.0], [20.0]], degrees=True))
    mid = shift_quat(quat, np.array([0, 1]), 0.5)
    xyzw = np.concatenate([mid[:, 1:], mid[:, :1]], axis=1)
    angles = Rotation.from_quat(xyzw).as_euler("zyx", degrees=True)
    np.testing.assert_allclose(angles[:, 0], [5.0, 15.0], atol=1e-9)


def test_field_norm_error():
    b = np.array([[1.1, 0.0, 0.0], [0.0, 0.9, 0.0], [np.nan, np.nan, np.nan], [0.0, 0.0, 5.0]])
    assert field_norm_error(b, np.array([True, True, True, False])) == pytest.approx(0.1)
    assert field_norm_error(b[:3]) == pytest.approx(0.1)


def test_bad_input_raises_imugraph_error():
    ref = _reference()
    with pytest.raises(ImugraphError, match="quat_est"):
        orientation_error(ref[:-1], ref, None, RATE)
    with pytest.raises(ImugraphError, match="mask"):
        orientation_error(ref, ref, np.zeros(N, bool), RATE)
    with pytest.raises(ImugraphError, match="b_mag_cal"):
        field_norm_error(np.ones((4, 2)))
