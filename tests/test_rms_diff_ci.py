"""benchmarks.common.rms_diff_ci: the block-bootstrap interval of a difference of RMS orientation errors."""

import numpy as np

from benchmarks.common import rms_diff_ci
from imugraph.geometry import expmap, rotmat_to_quat


def _quats_with_error(q_ref: np.ndarray, angle_rad: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """q_ref rotated in the body frame by angle_rad about a tilt axis (a heading fit cannot remove it)."""
    from imugraph.geometry import quat_mul
    dq = np.array([rotmat_to_quat(expmap(a * axis)) for a in angle_rad])
    return quat_mul(q_ref, dq)


def _slow_noise(rng, n: int, rms_deg: float) -> np.ndarray:
    """Errors correlated over ≈ 0.5 s (a fractional time shift cannot average them away), RMS `rms_deg`."""
    e = np.convolve(rng.standard_normal(n + 49), np.ones(50), "valid")
    return np.deg2rad(rms_deg) * e / np.sqrt(np.mean(e ** 2))


def test_interval_contains_zero_for_equal_systems_and_excludes_it_for_a_worse_one():
    rng = np.random.default_rng(1)
    n, rate = 6000, 100.0
    q_ref = np.array([rotmat_to_quat(expmap(np.array([0.0, 0.0, 0.3 * np.sin(0.01 * k)]))) for k in range(n)])
    x = np.array([1.0, 0.0, 0.0])
    e_a = _slow_noise(rng, n, 0.5)          # two systems with the same error statistics
    e_b = _slow_noise(rng, n, 0.5)
    lo, hi = rms_diff_ci(_quats_with_error(q_ref, e_a, x), _quats_with_error(q_ref, e_b, x), q_ref, None, rate)
    assert lo < 0.0 < hi and hi - lo < 0.2
    e_c = _slow_noise(rng, n, 0.8)           # RMS 0.8° against 0.5°: clearly worse
    lo, hi = rms_diff_ci(_quats_with_error(q_ref, e_c, x), _quats_with_error(q_ref, e_b, x), q_ref, None, rate)
    assert 0.0 < lo < 0.3 < hi
